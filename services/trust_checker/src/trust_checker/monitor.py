"""The evaluator: a spec compiled to closures (:mod:`trust_checker.compile`), stepped one
tick at a time, with the semantics of docs/trust_checker.md.

Per tick, :meth:`Monitor.step` takes the inputs (checked against their declared types),
pushes last tick's held values into the bounded histories, then runs one precomputed plan:
the computed streams in dependency order (offset-0 dependencies first), each updating its
stateful nodes and storing its value. Nothing walks the syntax tree at run time.

The plan depends on which inputs arrived (cached per set): a stream whose value is a
pure function of the held values of streams it reads at offset 0 (no ``x[k]`` with
k > 0, no stateful node, not a bare reference) is left out when none of those can have
changed at this tick; its value from the last tick stands, as a lifted stream ticks on
every tick. The first tick, and the tick after a run-time error, compute everything.

Finite traces: :meth:`Monitor.finish` runs the drain ticks after the last input, during
which a stream is computed while the tick is below ``T + extra`` (see the docs).
Hot swap: :meth:`Monitor.swap` builds a monitor for a new spec that keeps the held
values and histories of the streams that keep their names, and the operator state of the
streams whose equations did not change.
"""

from __future__ import annotations

import heapq
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from typing import Final, NamedTuple, NoReturn

from trust_checker.compile import (
    INF,
    Clock,
    Compiler,
    EvalNode,
    Node,
    StatefulNode,
    Stream,
    type_hint,
)
from trust_checker.errors import EvalError, InputError, Problem, SpecError
from trust_checker.lang import ast
from trust_checker.lang.check import Limits, check_spec, children
from trust_checker.operators import CALLS, Fault, Mismatch, conformer
from trust_checker.values import INT_MAX, INT_MIN, NOVAL

__all__ = ["Fired", "Monitor", "Output"]

_PURE: Final = frozenset(CALLS) | {"default", "is_defined", "init"}
"""Built-ins whose value is a function of their operands' held values (``init`` too,
under an operator: a stream whose root is ``init`` passes NoVal through and is never
skipped)."""


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


Runner = Callable[[], object]
"""Computes a stream's value at this tick (updating its stateful nodes first)."""


def _runner(s: Stream, updates: list[StatefulNode], cur: Callable[[], object]) -> Runner:
    widen = s.decl is not None and s.decl.type == ast.TName("Float")
    ups = tuple(u.update for u in updates)
    if not ups and not widen:
        return cur

    def run_full() -> object:
        for u in ups:
            u()
        v = cur()
        if widen and type(v) is int:
            v = float(v)
        return v

    return run_full


_new_output = tuple.__new__
"""``Output`` rows are built with ``tuple.__new__`` (the same tuple, without the Python
call of the generated ``__new__``)."""


def _walk(e: ast.Expr) -> Iterator[ast.Expr]:
    yield e
    for c in children(e):
        yield from _walk(c)


class Monitor:
    """A running spec. ``step`` takes one tick, ``finish`` drains a finite trace,
    ``swap`` hot-swaps the spec keeping stream history; see API.md."""

    def __init__(self, spec: ast.Spec, *, limits: Limits | None = None) -> None:
        self._limits = limits if limits is not None else Limits()
        problems = check_spec(spec, self._limits)
        if problems:
            raise SpecError(problems)
        self._spec = spec
        self._clock = Clock()
        self._tick = 0
        self._ran = False
        self._finished = False
        self.fired: list[Fired] = []
        self._build()

    # -- building -----------------------------------------------------------------------

    def _build(self) -> None:
        spec = self._spec
        self._streams: dict[str, Stream] = {}
        for d in spec.decls:
            self._streams[d.name] = Stream(d.name, d.kind, d)
        # input name -> (stream, the type a value may have to be taken as it is (None:
        # always conform it), conformer, the input's bit in a tick's mask)
        self._in: dict[str, tuple[Stream, type | None, Callable[[object], object], int]] = {}
        for i, d in enumerate(d for d in spec.decls if d.kind == "in"):
            plain = type_hint(d) if isinstance(d.type, ast.TName) else None
            self._in[d.name] = (self._streams[d.name], plain, conformer(d.type), 1 << i)
        # the computed streams: equations, then hidden ones (x[k] on an expression, triggers)
        self._exprs: dict[str, ast.Expr] = {eq.name: eq.expr for eq in spec.equations}
        self._owner: dict[str, str] = {}
        self._hidden_of: dict[int, Stream] = {}
        self._trigger_streams: list[tuple[Stream, ast.Trigger, int]] = []
        uses_eval = False
        for i, t in enumerate(spec.triggers):
            name = f"<trigger {i}>"
            s = Stream(name, "aux", None, hidden=True)
            self._streams[name] = s
            self._exprs[name] = t.cond
            self._owner[name] = f'trigger "{t.message}"'
            self._trigger_streams.append((s, t, i))
        pending = list(self._exprs.items())
        while pending:
            owner, root = pending.pop(0)
            for e in _walk(root):
                uses_eval = uses_eval or isinstance(e, ast.Eval)
                if isinstance(e, ast.Index) and not isinstance(e.expr, ast.Var):
                    name = f"<{self._owner.get(owner, owner)}: {e.pos}>"
                    dup = 1
                    while name in self._streams:
                        dup += 1
                        name = f"<{self._owner.get(owner, owner)}: {e.pos} #{dup}>"
                    s = Stream(name, "aux", None, hidden=True)
                    self._streams[name] = s
                    self._exprs[name] = e.expr
                    self._owner[name] = self._owner.get(owner, owner)
                    self._hidden_of[id(e)] = s
        # offset-0 dependencies and the evaluation order
        computed = list(self._exprs)
        deps: dict[str, set[str]] = {n: set() for n in computed}
        unscoped: list[str] = []
        for n in computed:
            self._deps(self._exprs[n], deps[n], unscoped, n)
        for n in dict.fromkeys(unscoped):
            dependents = self._dependents(n, deps)
            deps[n] |= {m for m in computed if m not in dependents and m not in unscoped}
        order = self._order(computed, deps)
        self._rank = {n: i for i, n in enumerate(order)}
        # history depths
        depth: dict[str, int] = {}
        for n in computed:
            for e in _walk(self._exprs[n]):
                if isinstance(e, ast.Index) and e.offset > 0:
                    target = e.expr.name if isinstance(e.expr, ast.Var) else None
                    key = target if target is not None else self._hidden_of[id(e)].name
                    depth[key] = max(depth.get(key, 0), e.offset)
        if uses_eval:
            for d in spec.decls:
                depth[d.name] = max(depth.get(d.name, 0), self._limits.dynamic_history)
        self._hist_push: list[tuple[Callable[[object], None], Stream]] = []
        for name, k in depth.items():
            s = self._streams[name]
            s.hist = deque([NOVAL] * k, maxlen=k)
            self._hist_push.append((s.hist.append, s))
        self._extras(computed)
        # compile, in order
        self._plan: list[tuple[Stream, Runner]] = []
        self._reads: dict[str, frozenset[str] | None] = {}
        """For a stream whose value is a pure function of the held values of the streams
        it reads at offset 0: those streams (see :meth:`_plan_for`)."""
        self._plans: dict[int, tuple[tuple[Stream, ...], list[tuple[Stream, Runner]]]] = {}
        """Per mask of inputs: the inputs (streams) and the plan (see _plan_for)."""
        self._full = True
        """Compute every stream at the next tick (the first, and after an error)."""
        self.nodes: dict[str, Node] = {}
        """The compiled root node of every computed stream (for inspection)."""
        self._stateful: dict[str, list[StatefulNode]] = {}
        problems: list[Problem] = []
        for name in order:
            s = self._streams[name]
            c = self._compiler(s)
            try:
                node = c.compile(self._exprs[name])
            except Fault as f:
                problems.append(self._problem(f))
                continue
            self.nodes[name] = node
            self._stateful[name] = c.stateful
            self._plan.append((s, _runner(s, c.stateful, node.cur)))
            if not c.stateful and node.cur is node.held:
                self._reads[name] = self._reads0(self._exprs[name])
        if problems:
            raise SpecError(problems)
        self._outputs = [self._streams[n] for n in spec.outputs]
        self._periodic = [
            (s, s.decl.period_ns)
            for s in self._outputs
            if s.decl is not None and s.decl.period_ns is not None
        ]
        self._due: dict[str, int] = {}
        self._last_mask = 0
        self._last_arrived: tuple[Stream, ...] = ()
        """The inputs given at the last tick (their ``cur`` goes back to NoVal)."""
        self._after = bool(self._periodic or self._trigger_streams)
        finite = [s.extra for s in self._outputs if s.extra < INF]
        finite += [s.extra for s, _, _ in self._trigger_streams if s.extra < INF]
        self._drain = max(finite, default=0)

    def _deps(self, e: ast.Expr, out: set[str], unscoped: list[str], owner: str) -> None:
        if isinstance(e, ast.Var):
            if self._streams[e.name].kind != "in":
                out.add(e.name)
            return
        if isinstance(e, ast.Index):
            if e.offset == 0:
                if isinstance(e.expr, ast.Var):
                    self._deps(e.expr, out, unscoped, owner)
                else:
                    out.add(self._hidden_of[id(e)].name)
            return
        if isinstance(e, ast.Eval):
            if e.scope is None:
                unscoped.append(owner)
            else:
                out.update(n for n in e.scope if self._streams[n].kind != "in")
        for c in children(e):
            self._deps(c, out, unscoped, owner)

    def _reads0(self, e: ast.Expr) -> frozenset[str] | None:
        """The streams ``e`` reads at offset 0, or None if its value can change without
        one of them changing (it reads the past: ``x[k]``, k > 0)."""
        out: set[str] = set()
        for x in _walk(e):
            if isinstance(x, ast.Var):
                out.add(x.name)
            elif isinstance(x, ast.Index):
                if x.offset > 0:
                    return None
                if not isinstance(x.expr, ast.Var):
                    out.add(self._hidden_of[id(x)].name)
            elif isinstance(x, ast.Eval | ast.Aggregate):
                return None
            elif isinstance(x, ast.Call) and x.func not in _PURE:
                return None
        return frozenset(out)

    def _plan_for(self, mask: int) -> tuple[tuple[Stream, ...], list[tuple[Stream, Runner]]]:
        """For a tick where the inputs in ``mask`` arrived: those inputs, and the streams
        to compute: every stream but those that are a pure function of held values none
        of which can have changed (their ``cur`` from the last tick stands: a lifted
        stream ticks on every tick). Cached per mask."""
        arrived = tuple(s for s, _, _, bit in self._in.values() if mask & bit)
        changed = {s.name for s in arrived}
        plan: list[tuple[Stream, Runner]] = []
        for s, run in self._plan:
            reads = self._reads.get(s.name)
            if reads is None or not reads.isdisjoint(changed):
                plan.append((s, run))
                changed.add(s.name)
        if len(plan) == len(self._plan):
            plan = self._plan
        if len(self._plans) < 4096:
            self._plans[mask] = (arrived, plan)
        return arrived, plan

    @staticmethod
    def _dependents(name: str, deps: dict[str, set[str]]) -> set[str]:
        """``name`` and every stream that needs it at offset 0, directly or not."""
        rev: dict[str, set[str]] = {n: set() for n in deps}
        for n, ds in deps.items():
            for d in ds:
                rev[d].add(n)
        seen = {name}
        todo = [name]
        while todo:
            for m in rev[todo.pop()]:
                if m not in seen:
                    seen.add(m)
                    todo.append(m)
        return seen

    def _order(self, computed: list[str], deps: dict[str, set[str]]) -> list[str]:
        index = {n: i for i, n in enumerate(computed)}
        missing = {n: len(ds) for n, ds in deps.items()}
        users: dict[str, list[str]] = {n: [] for n in computed}
        for n, ds in deps.items():
            for d in ds:
                users[d].append(n)
        ready = [index[n] for n, k in missing.items() if k == 0]
        heapq.heapify(ready)
        order: list[str] = []
        while ready:
            n = computed[heapq.heappop(ready)]
            order.append(n)
            for u in users[n]:
                missing[u] -= 1
                if missing[u] == 0:
                    heapq.heappush(ready, index[u])
        if len(order) != len(computed):
            stuck = [n for n in computed if n not in set(order)]
            raise SpecError(
                [
                    Problem(
                        self._spec.path,
                        0,
                        0,
                        "these streams need each other's value at the same tick: "
                        + ", ".join(self._owner.get(n, n) for n in stuck),
                        hint="read one of them in the past (x[1]) or scope the eval: "
                        "eval(s, {a, b})",
                    )
                ]
            )
        return order

    def _extras(self, computed: list[str]) -> None:
        """``extra`` per stream: how many drain ticks it runs past the last input tick."""
        for n in computed:
            self._streams[n].extra = INF

        def extra(e: ast.Expr) -> int:
            if isinstance(e, ast.Lit):
                return INF
            if isinstance(e, ast.Var):
                return self._streams[e.name].extra
            if isinstance(e, ast.Index):
                inner = (
                    extra(e.expr) if isinstance(e.expr, ast.Var) else (self._hidden_of[id(e)].extra)
                )
                return min(INF, inner + e.offset)
            return min((extra(c) for c in children(e)), default=INF)

        for _ in range(len(computed) + 1):
            changed = False
            for n in computed:
                s = self._streams[n]
                v = extra(self._exprs[n])
                if v < s.extra:
                    s.extra, changed = v, True
            if not changed:
                break

    def _compiler(self, owner: Stream) -> Compiler:
        def lookup(name: str, e: ast.Expr, offset: int) -> Stream:
            s = self._streams.get(name)
            if s is None or s.hidden:
                raise Fault(f"unknown stream '{name}'", f"{e.pos}")
            return s

        def hidden(e: ast.Index) -> Stream:
            s = self._hidden_of.get(id(e))
            if s is None:
                raise Fault(
                    "x[k] in an eval expression reads a stream by name: write name[k]",
                    f"{e.pos}",
                )
            return s

        def make_eval(e: ast.Eval, source: Node, c: Compiler) -> StatefulNode:
            return EvalNode(
                e, source, lambda: self._dynamic(owner, e), f"{self._spec.path}:{e.pos}"
            )

        return Compiler(
            path=self._spec.path,
            clock=self._clock,
            lookup=lookup,
            hidden=hidden,
            make_eval=make_eval,
            window_samples=self._limits.window_samples,
        )

    def _dynamic(self, owner: Stream, e: ast.Eval) -> Compiler:
        """A compiler for an eval expression computed as part of ``owner``."""
        rank = self._rank[owner.name]
        scope = e.scope
        names = sorted(n for n, s in self._streams.items() if not s.hidden)

        def lookup(name: str, at: ast.Expr, offset: int) -> Stream:
            if scope is not None and name not in scope:
                raise Fault(
                    f"'{name}' is not in the scope {{{', '.join(scope)}}} of this "
                    f"{e.kind} (add it to the scope)",
                    f"{at.pos}",
                )
            s = self._streams.get(name)
            if s is None or s.hidden:
                raise Fault(
                    f"unknown stream '{name}' (the spec's streams: {', '.join(names)})",
                    f"{at.pos}",
                )
            if offset == 0 and s.kind != "in" and self._rank[name] >= rank:
                raise Fault(
                    f"'{name}' is computed after {owner.name!r} in a tick, so its value "
                    f"now is not known here: read {name}[1], or name it in the scope",
                    f"{at.pos}",
                )
            return s

        def hidden(at: ast.Index) -> Stream:
            raise Fault(
                "x[k] in an eval expression reads a stream by name: write name[k]",
                f"{at.pos}",
            )

        def make_eval(inner: ast.Eval, source: Node, c: Compiler) -> StatefulNode:
            return EvalNode(
                inner, source, lambda: self._dynamic(owner, inner), f"{e.kind} expression"
            )

        return Compiler(
            path=f"<{e.kind} at {self._spec.path}:{e.pos}>",
            clock=self._clock,
            lookup=lookup,
            hidden=hidden,
            make_eval=make_eval,
            window_samples=self._limits.window_samples,
        )

    def _problem(self, f: Fault) -> Problem:
        line = col = 0
        parts = f.where.rsplit(":", 2)
        if len(parts) == 3 and parts[1].isdigit() and parts[2].isdigit():
            line, col = int(parts[1]), int(parts[2])
        text = ""
        lines = self._spec.source.splitlines()
        if 0 < line <= len(lines):
            text = lines[line - 1]
        return Problem(self._spec.path, line, col, f.message, text)

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
                f"the monitor has finished (finish() ran after tick {self._tick - 1}); "
                "create a new Monitor to check another trace"
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
            cached = self._plan_for(mask)
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
                + "; the tick was not taken, send a value of the declared type"
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

    def _drain_tick(
        self, ts_ns: int | None, plan: list[tuple[Stream, Runner]], stopped: list[Stream]
    ) -> list[Output]:
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

    def _abort(self, failed: Stream | None, plan: list[tuple[Stream, Runner]]) -> None:
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
        for j in range(self._drain):
            plan = [(s, r) for s, r in self._plan if j < s.extra < INF]
            stopped = [s for s in computed if not j < s.extra < INF]
            yield self._drain_tick(None, plan, stopped)

    def swap(self, new_spec: ast.Spec) -> Monitor:
        """A monitor for ``new_spec`` continuing this one: same tick count; streams with
        the same name keep their held values and history; streams whose equation is
        unchanged also keep their operators' state. Raises :class:`SpecError` (and this
        monitor stays as it was) if ``new_spec`` does not check."""
        new = Monitor(new_spec, limits=self._limits)
        new._tick, new._ran = self._tick, self._ran
        new._clock.ts = self._clock.ts
        for name, s in new._streams.items():
            old = self._streams.get(name)
            if old is None or old.hidden != s.hidden:
                continue
            if s.hidden and self._exprs.get(name) != new._exprs.get(name):
                continue
            s.held = old.held
            if s.hist is not None:
                past = list(old.hist) if old.hist is not None else []
                s.hist.extend(past[-(s.hist.maxlen or 0) :] if past else [])
            if name in new._stateful and self._exprs.get(name) == new._exprs.get(name):
                mine, theirs = new._stateful[name], self._stateful.get(name, [])
                if len(mine) == len(theirs):
                    for a, b in zip(mine, theirs, strict=True):
                        a.restore(b.export())
        if self._due:
            for s, period in new._periodic:
                now = self._clock.ts if self._clock.ts is not None else 0
                new._due[s.name] = self._due.get(s.name, now + period)
        return new
