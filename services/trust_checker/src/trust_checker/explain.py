"""Structured verdicts: why a Bool output turned false, and why a trigger fired.

:class:`Explainer` wraps a :class:`~trust_checker.engine.SpecRunner`; its :meth:`step`
returns the runner's outputs plus :class:`ExplainedVerdict` values:

- an **output verdict** when a Bool output turns false: its value is false at this tick
  and the last value it gave before was not false (true, ⊥, or none yet). A stream that
  stays false gives no further verdict until it has been something else in between;
- a **trigger verdict** for every firing of ``trigger COND "message" severity`` (every
  tick at which COND is true, as :attr:`SpecRunner.fired` lists them); its ``stream`` is
  ``trigger.<n>``, n the trigger's place among the spec's triggers (0-based).

``because`` lists what decided the value, depth-first from the verdict's expression:
each deciding operand's source text (as written in the spec) and value at this tick; an
input as its held value and the tick at which that value arrived (tracked here from the
inputs given to :meth:`step`); a stream the spec computes (an ``aux`` or another
output) as its value followed by the reasons inside its own equation. Only the operands
that decide the result are followed:

=======================  ==========================================================
``a && b``               false: the false operands (true: both)
``a || b``               true: the true operands (false: both)
``a => b``               false: both (true: a if false, else b)
``if c then a else b``   the condition and the branch taken
anything else            every operand (both sides of a comparison)
=======================  ==========================================================

and an operator whose value is ⊥ is explained by its ⊥ operands. Literals and
subexpressions that read no stream (``2.0 * 3.0``) are not listed, nor is a text
already listed, and the list is bounded
(``max_causes`` entries, ``max_depth`` levels; ``truncated`` says when it was cut).
``x[k]`` is a leaf: a past value, explained by the input tick it arrived at.

Values of subexpressions are read from the compiled nodes after the tick
(:attr:`SpecRunner.nodes`, ``node.value()``), so nothing is computed on the hot path
unless a verdict is due. Drain ticks (:meth:`finish`) are explained from the state
after the last one: a verdict at an earlier drain tick has no ``because`` and is marked
``truncated``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Final, NamedTuple, Protocol

from rap_schemas import TrustCause, TrustVerdict

from trust_checker.engine.runner import Output, SpecRunner
from trust_checker.errors import EvalError
from trust_checker.lang import ast
from trust_checker.lang.check import children
from trust_checker.lang.lexer import Lexeme, tokenize
from trust_checker.lang.parser import BINARY
from trust_checker.operators import Fault
from trust_checker.values import BOTTOM, NOVAL, UNIT, console, to_plain

__all__ = [
    "Cause",
    "Explained",
    "ExplainedVerdict",
    "Explainer",
    "expr_text",
    "to_message",
]

MAX_TEXT: Final = 200
"""Longest subexpression text given (longer is cut with "...")."""


class _NodeView(Protocol):
    """What explanations read of a compiled node (``trust_checker.engine.nodes.ExprNode``)."""

    @property
    def ast(self) -> ast.Expr: ...
    @property
    def children(self) -> tuple[_NodeView, ...]: ...
    def value(self) -> object: ...


@dataclass(frozen=True, slots=True)
class Cause:
    """One entry of ``because``: ``expr`` (source text) had ``value`` at the verdict's
    tick; for an input's value, ``input`` names it and ``input_tick`` is the tick its
    value arrived at (None when there is none: ⊥)."""

    expr: str
    value: object
    depth: int = 0
    input: str | None = None
    input_tick: int | None = None

    def describe(self) -> str:
        text = f"{self.expr} = {console(self.value)}"
        if self.input is not None:
            text += (
                f" (input {self.input}, tick {self.input_tick})"
                if self.input_tick is not None
                else f" (input {self.input}, no value yet)"
            )
        return text


@dataclass(frozen=True, slots=True)
class ExplainedVerdict:
    """An output that turned false (``kind="output"``) or a trigger that fired."""

    stream: str
    tick: int
    ts_ns: int | None
    value: object
    expr: str
    because: tuple[Cause, ...]
    kind: str = "output"
    message: str = ""
    severity: str | None = None
    truncated: bool = False

    def describe(self) -> str:
        """A human form: the verdict on one line, then one indented line per cause."""
        head = f"{self.stream}[{self.tick}] = {console(self.value)}"
        if self.kind == "trigger":
            head = f'{self.severity} "{self.message}" at tick {self.tick} ({self.stream})'
        lines = [f"{head}: {self.expr}"]
        lines += [f"{'  ' * (c.depth + 1)}because {c.describe()}" for c in self.because]
        if self.truncated:
            lines.append("  ...")
        return "\n".join(lines)


class Explained(NamedTuple):
    outputs: list[Output]
    verdicts: list[ExplainedVerdict]


def to_message(v: ExplainedVerdict) -> TrustVerdict:
    """The wire form (``rap.TrustVerdict``): values as plain data."""
    sev = v.severity
    return TrustVerdict(
        stream=v.stream,
        tick=v.tick,
        ts=v.ts_ns,
        value=to_plain(v.value),
        kind="trigger" if v.kind == "trigger" else "output",
        expr=v.expr,
        because=[
            TrustCause(
                expr=c.expr,
                value=to_plain(c.value),
                deferred=c.value is BOTTOM,
                depth=c.depth,
                input=c.input,
                input_tick=c.input_tick,
            )
            for c in v.because
        ],
        truncated=v.truncated,
        message=v.message,
        severity=sev if sev in ("info", "warning", "error", "critical") else None,  # type: ignore[arg-type]
    )


# -- source text -----------------------------------------------------------------------

_OPEN: Final = {"(": ")", "[": "]", "{": "}"}
_CLOSE: Final = frozenset(_OPEN.values())


def _walk(e: ast.Expr) -> Iterator[ast.Expr]:
    yield e
    for c in children(e):
        yield from _walk(c)


class _Source:
    """The spec's tokens, to give each subexpression as it was written."""

    def __init__(self, spec: ast.Spec) -> None:
        toks: list[Lexeme] = []
        if spec.source:
            toks, _ = tokenize(spec.source, spec.path)
        self.toks = [t for t in toks if t.kind != "EOF"]
        self.at = {(t.line, t.col): i for i, t in enumerate(self.toks)}
        self.cache: dict[int, str] = {}

    def text(self, e: ast.Expr) -> str:
        key = id(e)
        found = self.cache.get(key)
        if found is None:
            found = self._span(e)
            if found is None:
                found = expr_text(e)
            if len(found) > MAX_TEXT:
                found = found[: MAX_TEXT - 3] + "..."
            self.cache[key] = found
        return found

    def _span(self, e: ast.Expr) -> str | None:
        own = self.at.get((e.pos.line, e.pos.col))
        if own is None:
            return None
        toks = self.toks
        lo = hi = own
        for n in _walk(e):
            i = self.at.get((n.pos.line, n.pos.col))
            if i is None:
                continue
            if isinstance(n, ast.Lit) and toks[i].kind == "-" and i + 1 < len(toks):
                i += 1  # a negative literal starts at its sign
            lo, hi = min(lo, i), max(hi, i)
        # take in the brackets the span opens or closes: f( .. ), x[ .. ], ( .. ) * c
        missing = depth = 0
        for t in toks[lo : hi + 1]:
            if t.kind in _OPEN:
                depth += 1
            elif t.kind in _CLOSE:
                if depth:
                    depth -= 1
                else:
                    missing += 1
        while missing and lo > 0:
            lo -= 1
            if toks[lo].kind in _CLOSE:
                missing += 1
            elif toks[lo].kind in _OPEN:
                missing -= 1
        depth = 0
        for t in toks[lo : hi + 1]:
            if t.kind in _OPEN:
                depth += 1
            elif t.kind in _CLOSE:
                depth = max(depth - 1, 0)
        while depth and hi + 1 < len(toks):
            hi += 1
            if toks[hi].kind in _OPEN:
                depth += 1
            elif toks[hi].kind in _CLOSE:
                depth -= 1
        parts = [toks[lo].text]
        for i in range(lo + 1, hi + 1):
            if toks[i].start != toks[i - 1].end:
                parts.append(" ")  # any gap (spaces, newlines, comments) is one space
            parts.append(toks[i].text)
        return "".join(parts)


def _lit_text(v: object) -> str:
    if v is True:
        return "true"
    if v is False:
        return "false"
    if v is UNIT:
        return "()"
    if isinstance(v, str):
        out = v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")
        return '"' + out.replace("\t", "\\t") + '"'
    if isinstance(v, float):
        text = repr(v)
        return text if any(c in text for c in ".en") else text + ".0"
    return str(v)


def expr_text(e: ast.Expr, outer: int = 0) -> str:
    """``e`` written in the spec language (for trees without source text); ``outer`` is
    the binding power of the context (parentheses where needed)."""

    def wrap(text: str, prec: int) -> str:
        return f"({text})" if prec < outer else text

    match e:
        case ast.Lit(value=v):
            return _lit_text(v)
        case ast.Var(name=n):
            return n
        case ast.Index(expr=x, offset=k):
            return f"{expr_text(x, 10)}[{k}]"
        case ast.Unary(op="!", operand=ast.Binary(op="==", left=a, right=b)):
            return wrap(f"{expr_text(a, 6)} != {expr_text(b, 6)}", 5)
        case ast.Unary(op=o, operand=x):
            return wrap(f"{o}{expr_text(x, 9)}", 9)
        case ast.Binary(op=o, left=a, right=b):
            p, right_assoc = BINARY[o]
            left = expr_text(a, p + 1 if right_assoc else p)
            right = expr_text(b, p if right_assoc else p + 1)
            return wrap(f"{left} {o} {right}", p)
        case ast.If(cond=c, then=a, else_=b):
            return wrap(f"if {expr_text(c)} then {expr_text(a)} else {expr_text(b)}", 0)
        case ast.Call(func="timeout", args=(x, ast.Lit(value=ns))):
            return f"timeout({expr_text(x)}, {ns}ns)"
        case ast.Call(func=f, args=xs):
            return f"{f}({', '.join(expr_text(x) for x in xs)})"
        case ast.Eval(source=s, kind=k):
            return f"{k}({expr_text(s)})"
        case ast.ListLit(items=xs):
            return f"[{', '.join(expr_text(x) for x in xs)}]"
        case ast.TupleLit(items=xs):
            return f"({', '.join(expr_text(x) for x in xs)})"
        case ast.MapLit(pairs=ps):
            return "Map(" + ", ".join(f"{_lit_text(k)}: {expr_text(x)}" for k, x in ps) + ")"
        case ast.StructLit(fields=fs):
            return "{" + ", ".join(f"{k}: {expr_text(x)}" for k, x in fs) + "}"
        case ast.Field(expr=x, name=n):
            return f"{expr_text(x, 10)}.{n}"
        case ast.Aggregate(expr=x, window_ns=w, using=u):
            return f"{expr_text(x, 10)}.aggregate(over: {w}ns, using: {u})"


# -- the explainer ---------------------------------------------------------------------


def _value(n: _NodeView) -> object:
    try:
        return n.value()
    except Fault:  # not computable on its own (e.g. an operand that failed): skip it
        return NOVAL


def _is_input_leaf(e: ast.Expr) -> bool:
    """``x[k]`` on a stream, or the D5.2 ``x[-k, d]`` (``default(x[k], d)``)."""
    if isinstance(e, ast.Index):
        return True
    return (
        isinstance(e, ast.Call)
        and e.func == "default"
        and len(e.args) == 2
        and isinstance(e.args[0], ast.Index)
        and e.args[0].pos == e.pos
    )


class _Walk:
    """One verdict's ``because``."""

    __slots__ = ("causes", "ex", "seen", "truncated")

    def __init__(self, ex: Explainer) -> None:
        self.ex = ex
        self.causes: list[Cause] = []
        self.seen: set[str] = set()
        self.truncated = False

    def root(self, node: _NodeView) -> None:
        e = node.ast
        if isinstance(e, ast.Var) or _is_input_leaf(e):
            self.visit(node, 0)  # ok = x: the input (or stream) itself is the reason
            return
        self.seen.add(self.ex._source.text(e))
        for k in _deciding(node, _value(node)):
            self.visit(k, 0, _chain(e))

    def add(self, cause: Cause) -> bool:
        if len(self.causes) >= self.ex.max_causes:
            self.truncated = True
            return False
        self.causes.append(cause)
        return True

    def visit(self, node: _NodeView, depth: int, chain: str = "") -> None:
        """``chain``: the parent's operator when it is ``&&`` or ``||``; a child with the
        same operator is part of the same chain (``a && b && c``), not a level."""
        if self.truncated:
            return
        e = node.ast
        ex = self.ex
        if isinstance(e, ast.Lit) or ex._constant(e):
            return
        v = _value(node)
        if v is NOVAL:
            return
        op = _chain(e)
        if op and op == chain:
            for k in _deciding(node, v):
                self.visit(k, depth, op)
            return
        text = ex._source.text(e)
        fresh = text not in self.seen
        self.seen.add(text)
        if isinstance(e, ast.Var):
            if e.name in ex._inputs:
                if fresh:
                    self.add(Cause(text, v, depth, e.name, ex._last.get(e.name)))
                return
            if fresh and not self.add(Cause(text, v, depth)):
                return
            sub = ex.runner.nodes.get(e.name)
            if sub is not None and depth + 1 < ex.max_depth:
                self.visit(sub, depth + 1)
            elif sub is not None:
                self.truncated = True
            return
        if _is_input_leaf(e):
            if fresh:
                self.add(ex._leaf(e, text, v, depth))
            return
        if fresh:
            if not self.add(Cause(text, v, depth)):
                return
            depth += 1
        kids = _deciding(node, v)
        if kids and depth >= ex.max_depth:
            self.truncated = True
            return
        for k in kids:
            self.visit(k, depth, op)


_READS: Final = (ast.Var, ast.Index, ast.Eval, ast.Aggregate)


def _chain(e: ast.Expr) -> str:
    return e.op if isinstance(e, ast.Binary) and e.op in ("&&", "||") else ""


def _deciding(node: _NodeView, v: object) -> Sequence[_NodeView]:
    """The operands of ``node`` that decide its value ``v`` (the table above)."""
    kids = node.children
    e = node.ast
    if not kids or isinstance(e, ast.Index):
        return ()
    if v is BOTTOM and not isinstance(e, ast.If | ast.Call | ast.Eval):
        bottoms = [k for k in kids if _value(k) is BOTTOM]
        if bottoms:
            return bottoms
    if isinstance(e, ast.Binary) and len(kids) == 2:
        a, b = kids
        if e.op in ("&&", "||"):
            decisive = e.op == "||"  # the value that decides alone
            if v is decisive:
                return [k for k in kids if _value(k) is decisive]
            return kids
        if e.op == "=>":
            if v is True:
                return [a] if _value(a) is False else [b]
            return kids
        return kids
    if isinstance(e, ast.If) and len(kids) == 3:
        c = _value(kids[0])
        if c is True:
            return kids[:2]
        if c is False:
            return (kids[0], kids[2])
        return kids[:1]
    return kids


class Explainer:
    """Wraps ``runner``: :meth:`step` gives the outputs and the verdicts of a tick.
    Use it instead of the runner (it tracks at which tick each input value arrived)."""

    def __init__(self, runner: SpecRunner, *, max_causes: int = 16, max_depth: int = 8) -> None:
        if max_causes < 1 or max_depth < 1:
            raise ValueError("max_causes and max_depth must be at least 1")
        self.runner = runner
        self.max_causes = max_causes
        self.max_depth = max_depth
        spec = runner.spec
        self._inputs = frozenset(spec.inputs)
        self._outputs = frozenset(spec.outputs)
        self._source = _Source(spec)
        self._constants: dict[int, bool] = {}
        self._last: dict[str, int] = {}
        """Input -> the tick its held value arrived at."""
        self._prev: dict[str, object] = {}
        """Output -> the last value it gave (NoVal never)."""
        depth: dict[str, int] = {}
        exprs = [eq.expr for eq in spec.equations] + [t.cond for t in spec.triggers]
        for root in exprs:
            for n in _walk(root):
                if (
                    isinstance(n, ast.Index)
                    and isinstance(n.expr, ast.Var)
                    and n.expr.name in self._inputs
                ):
                    depth[n.expr.name] = max(depth.get(n.expr.name, 0), n.offset)
        self._arrivals: dict[str, deque[int]] = {
            name: deque(maxlen=k + 1) for name, k in depth.items() if k > 0
        }
        """Input read at x[k], k > 0 -> its last k+1 arrival ticks."""
        by_ast = {id(n.ast): n for n in runner.nodes.values()}
        self._triggers: list[tuple[ast.Trigger, _NodeView | None]] = [
            (t, by_ast.get(id(t.cond))) for t in spec.triggers
        ]

    # -- stepping ------------------------------------------------------------------------

    @property
    def tick(self) -> int:
        return self.runner.tick

    def step(self, inputs: Mapping[str, object], ts_ns: int | None = None) -> Explained:
        """One tick of the runner (same errors: ``InputError``, the tick not taken;
        ``EvalError``, the tick taken and its outputs lost) and its verdicts."""
        tick = self.runner.tick
        try:
            outs = self.runner.step(inputs, ts_ns)
        except EvalError:
            self._arrived(inputs, tick)
            raise
        self._arrived(inputs, tick)
        return Explained(outs, self._verdicts(outs, ts_ns, tick))

    def finish(self) -> Explained:
        """The drain ticks of a finite trace (:meth:`SpecRunner.drain`) and their verdicts,
        each explained at its own drain tick."""
        outs: list[Output] = []
        verdicts: list[ExplainedVerdict] = []
        for tick in self.drain():
            outs += tick.outputs
            verdicts += tick.verdicts
        return Explained(outs, verdicts)

    def drain(self) -> Iterator[Explained]:
        """:meth:`finish` one drain tick at a time."""
        for tick_outs in self.runner.drain():
            yield Explained(tick_outs, self._verdicts(tick_outs, None, self.runner.tick - 1))

    def swap(self, spec: ast.Spec) -> Explainer:
        """An explainer over ``runner.swap(spec)``; input arrival ticks and the outputs'
        last values carry over for the streams that keep their names."""
        new = Explainer(
            self.runner.swap(spec), max_causes=self.max_causes, max_depth=self.max_depth
        )
        new._last = {k: t for k, t in self._last.items() if k in new._inputs}
        new._prev = {k: v for k, v in self._prev.items() if k in new._outputs}
        for name, q in new._arrivals.items():
            q.extend(self._arrivals.get(name, ()))
            if not q and name in new._last:
                q.append(new._last[name])
        return new

    def _arrived(self, inputs: Mapping[str, object], tick: int) -> None:
        if self.runner.tick == tick:
            return  # not taken
        for name, v in inputs.items():
            if v is not NOVAL:
                self._last[name] = tick
                q = self._arrivals.get(name)
                if q is not None:
                    q.append(tick)

    def _verdicts(
        self, outs: Sequence[Output], ts_ns: int | None, now: int
    ) -> list[ExplainedVerdict]:
        verdicts: list[ExplainedVerdict] = []
        prev = self._prev
        for o in outs:
            if o.value is False and prev.get(o.stream) is not False:
                node = self.runner.nodes.get(o.stream)
                verdicts.append(self._verdict(o.stream, o.tick, o.ts_ns, False, node, now))
            prev[o.stream] = o.value
        fired = self.runner.fired
        if fired:
            verdicts += self._fired(now, ts_ns)
        return verdicts

    def _verdict(
        self,
        stream: str,
        tick: int,
        ts_ns: int | None,
        value: object,
        node: _NodeView | None,
        now: int,
        trigger: ast.Trigger | None = None,
    ) -> ExplainedVerdict:
        because: tuple[Cause, ...] = ()
        truncated = True
        expr = ""
        if node is not None:
            expr = self._source.text(node.ast)
            if tick == now:
                w = _Walk(self)
                w.root(node)
                because, truncated = tuple(w.causes), w.truncated
        if trigger is None:
            return ExplainedVerdict(stream, tick, ts_ns, value, expr, because, truncated=truncated)
        return ExplainedVerdict(
            stream,
            tick,
            ts_ns,
            value,
            expr or self._source.text(trigger.cond),
            because,
            kind="trigger",
            message=trigger.message,
            severity=trigger.severity,
            truncated=truncated,
        )

    def _fired(self, now: int, ts_ns: int | None) -> list[ExplainedVerdict]:
        """SpecRunner.fired, in trigger order, each as a verdict on ``trigger.<index>``."""
        out: list[ExplainedVerdict] = []
        for f in self.runner.fired:
            t, node = self._triggers[f.trigger]
            out.append(self._verdict(f"trigger.{f.trigger}", f.tick, f.ts_ns, True, node, now, t))
        return out

    def _constant(self, e: ast.Expr) -> bool:
        """``e`` reads no stream (``2.0 * 3.0``): not a reason worth listing."""
        key = id(e)
        found = self._constants.get(key)
        if found is None:
            found = not any(isinstance(n, _READS) for n in _walk(e))
            self._constants[key] = found
        return found

    def _leaf(self, e: ast.Expr, text: str, v: object, depth: int) -> Cause:
        """``x[k]`` (or ``x[-k, d]``): an input's value k ticks ago and its arrival tick."""
        idx = e if isinstance(e, ast.Index) else e.args[0]  # type: ignore[union-attr]
        assert isinstance(idx, ast.Index)
        target = idx.expr
        if not isinstance(target, ast.Var) or target.name not in self._inputs:
            return Cause(text, v, depth)
        name = target.name
        at = self.runner.tick - 1 - idx.offset
        arrived: int | None = None
        if idx.offset == 0:
            arrived = self._last.get(name)
        else:
            for t in reversed(self._arrivals.get(name, ())):
                if t <= at:
                    arrived = t
                    break
        return Cause(text, v, depth, name, arrived)
