"""Laying a checked spec out for running: its streams, the order they are computed in,
their histories and their compiled nodes.

:class:`CompiledSpec` takes a spec that checks (:func:`trust_checker.lang.check_spec`)
and builds everything the runner (:mod:`.runner`) steps, once: a :class:`~.nodes.Stream`
slot per declared stream and per hidden one (``x[k]`` on an expression, each trigger's
condition), the offset-0 dependencies and the evaluation order (a stable topological
order; an unscoped ``eval`` is computed after everything that does not need it), the
history depth of every stream read in the past, the drain length of a finite trace
(``extra``, docs/trust_checker.md, "Finite traces") and, in order, each computed
stream's compiled root node and the step that computes it.

The plan depends on which inputs arrived (:meth:`CompiledSpec.plan_for`, cached per set):
a stream whose value is a pure function of the held values of streams it reads at offset
0 (no ``x[k]`` with k > 0, no stateful node, not a bare reference) is left out when none
of those can have changed at this tick; its value from the last tick stands, as a lifted
stream ticks on every tick.
"""

from __future__ import annotations

import heapq
from collections import deque
from collections.abc import Callable, Iterator
from typing import Final

from trust_checker.engine.compiler import Compiler
from trust_checker.engine.dynamic import EvalNode
from trust_checker.engine.nodes import INF, ExprNode, StatefulNode, Stream, TickTime, type_hint
from trust_checker.errors import Problem, SpecError
from trust_checker.lang import ast
from trust_checker.lang.check import Limits, check_spec, children
from trust_checker.operators import CALLS, Fault, conformer
from trust_checker.values import NOVAL

__all__ = ["CompiledSpec", "Compute", "InputSlot", "Plan", "stream_compute", "walk"]

_PURE: Final = frozenset(CALLS) | {"default", "is_defined", "init"}
"""Built-ins whose value is a function of their operands' held values (``init`` too,
under an operator: a stream whose root is ``init`` passes NoVal through and is never
skipped)."""

Compute = Callable[[], object]
"""Computes a stream's value at this tick (updating its stateful nodes first)."""

Plan = list[tuple[Stream, Compute]]
"""Streams to compute at a tick, in order, each with its step."""

InputSlot = tuple[Stream, type | None, Callable[[object], object], int]
"""An input's stream, the type a value may have to be taken as it is (None: always
conform it), its conformer, and its bit in a tick's mask of inputs."""


def stream_compute(s: Stream, updates: list[StatefulNode], cur: Callable[[], object]) -> Compute:
    """The step computing ``s``: its stateful nodes' updates, then its root's ``cur``
    (an Int widened for a stream declared Float)."""
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


def walk(e: ast.Expr) -> Iterator[ast.Expr]:
    """``e`` and every expression under it, depth-first."""
    yield e
    for c in children(e):
        yield from walk(c)


class CompiledSpec:
    """A spec laid out for running (see the module docstring). Raises
    :class:`SpecError` if the spec does not check or an expression cannot be compiled.
    The streams' slots hold the run's state; one runner owns them."""

    def __init__(self, spec: ast.Spec, limits: Limits) -> None:
        found = check_spec(spec, limits)
        if found:
            raise SpecError(found)
        self.spec = spec
        self.limits = limits
        self.time = TickTime()
        """The current tick's timestamp, shared with the real-time nodes."""
        self.streams: dict[str, Stream] = {}
        for d in spec.decls:
            self.streams[d.name] = Stream(d.name, d.kind, d)
        self.inputs: dict[str, InputSlot] = {}
        """Input name -> its slot (see :data:`InputSlot`)."""
        for i, d in enumerate(d for d in spec.decls if d.kind == "in"):
            plain = type_hint(d) if isinstance(d.type, ast.TName) else None
            self.inputs[d.name] = (self.streams[d.name], plain, conformer(d.type), 1 << i)
        # the computed streams: equations, then hidden ones (x[k] on an expression, triggers)
        self.exprs: dict[str, ast.Expr] = {eq.name: eq.expr for eq in spec.equations}
        self.owner: dict[str, str] = {}
        self.hidden_of: dict[int, Stream] = {}
        self.triggers: list[tuple[Stream, ast.Trigger, int]] = []
        uses_eval = False
        for i, t in enumerate(spec.triggers):
            name = f"<trigger {i}>"
            s = Stream(name, "aux", None, hidden=True)
            self.streams[name] = s
            self.exprs[name] = t.cond
            self.owner[name] = f'trigger "{t.message}"'
            self.triggers.append((s, t, i))
        pending = list(self.exprs.items())
        while pending:
            owner, root = pending.pop(0)
            for e in walk(root):
                uses_eval = uses_eval or isinstance(e, ast.Eval)
                if isinstance(e, ast.Index) and not isinstance(e.expr, ast.Var):
                    name = f"<{self.owner.get(owner, owner)}: {e.pos}>"
                    dup = 1
                    while name in self.streams:
                        dup += 1
                        name = f"<{self.owner.get(owner, owner)}: {e.pos} #{dup}>"
                    s = Stream(name, "aux", None, hidden=True)
                    self.streams[name] = s
                    self.exprs[name] = e.expr
                    self.owner[name] = self.owner.get(owner, owner)
                    self.hidden_of[id(e)] = s
        # offset-0 dependencies and the evaluation order
        computed = list(self.exprs)
        deps: dict[str, set[str]] = {n: set() for n in computed}
        unscoped: list[str] = []
        for n in computed:
            self._deps(self.exprs[n], deps[n], unscoped, n)
        for n in dict.fromkeys(unscoped):
            dependents = self._dependents(n, deps)
            deps[n] |= {m for m in computed if m not in dependents and m not in unscoped}
        order = self._order(computed, deps)
        self.rank = {n: i for i, n in enumerate(order)}
        # history depths
        depth: dict[str, int] = {}
        for n in computed:
            for e in walk(self.exprs[n]):
                if isinstance(e, ast.Index) and e.offset > 0:
                    target = e.expr.name if isinstance(e.expr, ast.Var) else None
                    key = target if target is not None else self.hidden_of[id(e)].name
                    depth[key] = max(depth.get(key, 0), e.offset)
        if uses_eval:
            for d in spec.decls:
                depth[d.name] = max(depth.get(d.name, 0), self.limits.dynamic_history)
        self.hist_push: list[tuple[Callable[[object], None], Stream]] = []
        for name, k in depth.items():
            s = self.streams[name]
            s.hist = deque([NOVAL] * k, maxlen=k)
            self.hist_push.append((s.hist.append, s))
        self._extras(computed)
        # compile, in order
        self.plan: Plan = []
        self.reads: dict[str, frozenset[str] | None] = {}
        """For a stream whose value is a pure function of the held values of the streams
        it reads at offset 0: those streams (see :meth:`plan_for`)."""
        self.plans: dict[int, tuple[tuple[Stream, ...], Plan]] = {}
        """Per mask of inputs: the inputs (streams) and the plan (see :meth:`plan_for`)."""
        self.nodes: dict[str, ExprNode] = {}
        """The compiled root node of every computed stream (for inspection)."""
        self.stateful: dict[str, list[StatefulNode]] = {}
        problems: list[Problem] = []
        for name in order:
            s = self.streams[name]
            c = self._compiler(s)
            try:
                node = c.compile(self.exprs[name])
            except Fault as f:
                problems.append(self._problem(f))
                continue
            self.nodes[name] = node
            self.stateful[name] = c.stateful
            self.plan.append((s, stream_compute(s, c.stateful, node.cur)))
            if not c.stateful and node.cur is node.held:
                self.reads[name] = self._reads0(self.exprs[name])
        if problems:
            raise SpecError(problems)
        self.outputs = [self.streams[n] for n in spec.outputs]
        """The output streams, in console order."""
        self.periodic = [
            (s, s.decl.period_ns)
            for s in self.outputs
            if s.decl is not None and s.decl.period_ns is not None
        ]
        self.after = bool(self.periodic or self.triggers)
        finite = [s.extra for s in self.outputs if s.extra < INF]
        finite += [s.extra for s, _, _ in self.triggers if s.extra < INF]
        self.drain_ticks = max(finite, default=0)

    def _deps(self, e: ast.Expr, out: set[str], unscoped: list[str], owner: str) -> None:
        if isinstance(e, ast.Var):
            if self.streams[e.name].kind != "in":
                out.add(e.name)
            return
        if isinstance(e, ast.Index):
            if e.offset == 0:
                if isinstance(e.expr, ast.Var):
                    self._deps(e.expr, out, unscoped, owner)
                else:
                    out.add(self.hidden_of[id(e)].name)
            return
        if isinstance(e, ast.Eval):
            if e.scope is None:
                unscoped.append(owner)
            else:
                out.update(n for n in e.scope if self.streams[n].kind != "in")
        for c in children(e):
            self._deps(c, out, unscoped, owner)

    def _reads0(self, e: ast.Expr) -> frozenset[str] | None:
        """The streams ``e`` reads at offset 0, or None if its value can change without
        one of them changing (it reads the past: ``x[k]``, k > 0)."""
        out: set[str] = set()
        for x in walk(e):
            if isinstance(x, ast.Var):
                out.add(x.name)
            elif isinstance(x, ast.Index):
                if x.offset > 0:
                    return None
                if not isinstance(x.expr, ast.Var):
                    out.add(self.hidden_of[id(x)].name)
            elif isinstance(x, ast.Eval | ast.Aggregate):
                return None
            elif isinstance(x, ast.Call) and x.func not in _PURE:
                return None
        return frozenset(out)

    def plan_for(self, mask: int) -> tuple[tuple[Stream, ...], Plan]:
        """For a tick where the inputs in ``mask`` arrived: those inputs, and the streams
        to compute: every stream but those that are a pure function of held values none
        of which can have changed (their ``cur`` from the last tick stands: a lifted
        stream ticks on every tick). Cached per mask."""
        arrived = tuple(s for s, _, _, bit in self.inputs.values() if mask & bit)
        changed = {s.name for s in arrived}
        plan: Plan = []
        for s, run in self.plan:
            reads = self.reads.get(s.name)
            if reads is None or not reads.isdisjoint(changed):
                plan.append((s, run))
                changed.add(s.name)
        if len(plan) == len(self.plan):
            plan = self.plan
        if len(self.plans) < 4096:
            self.plans[mask] = (arrived, plan)
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
                        self.spec.path,
                        0,
                        0,
                        "these streams need each other's value at the same tick: "
                        + ", ".join(self.owner.get(n, n) for n in stuck),
                        hint="read one of them in the past (x[1]) or scope the eval: "
                        "eval(s, {a, b})",
                    )
                ]
            )
        return order

    def _extras(self, computed: list[str]) -> None:
        """``extra`` per stream: how many drain ticks it runs past the last input tick."""
        for n in computed:
            self.streams[n].extra = INF

        def extra(e: ast.Expr) -> int:
            if isinstance(e, ast.Lit):
                return INF
            if isinstance(e, ast.Var):
                return self.streams[e.name].extra
            if isinstance(e, ast.Index):
                inner = (
                    extra(e.expr) if isinstance(e.expr, ast.Var) else (self.hidden_of[id(e)].extra)
                )
                return min(INF, inner + e.offset)
            return min((extra(c) for c in children(e)), default=INF)

        for _ in range(len(computed) + 1):
            changed = False
            for n in computed:
                s = self.streams[n]
                v = extra(self.exprs[n])
                if v < s.extra:
                    s.extra, changed = v, True
            if not changed:
                break

    def _compiler(self, owner: Stream) -> Compiler:
        def lookup(name: str, e: ast.Expr, offset: int) -> Stream:
            s = self.streams.get(name)
            if s is None or s.hidden:
                raise Fault(f"unknown stream '{name}'", f"{e.pos}")
            return s

        def hidden(e: ast.Index) -> Stream:
            s = self.hidden_of.get(id(e))
            if s is None:
                raise Fault(
                    "x[k] in an eval expression reads a stream by name: write name[k]",
                    f"{e.pos}",
                )
            return s

        def make_eval(e: ast.Eval, source: ExprNode, c: Compiler) -> StatefulNode:
            return EvalNode(e, source, lambda: self._dynamic(owner, e), f"{self.spec.path}:{e.pos}")

        return Compiler(
            path=self.spec.path,
            clock=self.time,
            lookup=lookup,
            hidden=hidden,
            make_eval=make_eval,
            window_samples=self.limits.window_samples,
        )

    def _dynamic(self, owner: Stream, e: ast.Eval) -> Compiler:
        """A compiler for an eval expression computed as part of ``owner``."""
        rank = self.rank[owner.name]
        scope = e.scope
        names = sorted(n for n, s in self.streams.items() if not s.hidden)

        def lookup(name: str, at: ast.Expr, offset: int) -> Stream:
            if scope is not None and name not in scope:
                raise Fault(
                    f"'{name}' is not in the scope {{{', '.join(scope)}}} of this "
                    f"{e.kind} (add it to the scope)",
                    f"{at.pos}",
                )
            s = self.streams.get(name)
            if s is None or s.hidden:
                raise Fault(
                    f"unknown stream '{name}' (the spec's streams: {', '.join(names)})",
                    f"{at.pos}",
                )
            if offset == 0 and s.kind != "in" and self.rank[name] >= rank:
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

        def make_eval(inner: ast.Eval, source: ExprNode, c: Compiler) -> StatefulNode:
            return EvalNode(
                inner, source, lambda: self._dynamic(owner, inner), f"{e.kind} expression"
            )

        return Compiler(
            path=f"<{e.kind} at {self.spec.path}:{e.pos}>",
            clock=self.time,
            lookup=lookup,
            hidden=hidden,
            make_eval=make_eval,
            window_samples=self.limits.window_samples,
        )

    def _problem(self, f: Fault) -> Problem:
        line = col = 0
        parts = f.where.rsplit(":", 2)
        if len(parts) == 3 and parts[1].isdigit() and parts[2].isdigit():
            line, col = int(parts[1]), int(parts[2])
        text = ""
        lines = self.spec.source.splitlines()
        if 0 < line <= len(lines):
            text = lines[line - 1]
        return Problem(self.spec.path, line, col, f.message, text)
