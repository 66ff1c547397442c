"""Compiling expressions into closures (no Python source, no ``compile``/``exec``).

Each AST node becomes a :class:`Node`: its AST node, its operand nodes and three closures:

- ``held()``: the node's held value at the current tick (its latest value that was not
  NoVal; NoVal until it has had one). Operators call their operands' ``held`` - that is
  how "operators hold their operands" is implemented.
- ``cur()``: the value at this tick, NoVal where the node did not tick. It differs from
  ``held`` only for the nodes that pass NoVal through: a bare reference, ``latch``,
  ``init`` once its operand has had a value, and ``eval``.
- ``started``: ``None`` if the node always has a value, else a closure telling whether it
  has had one yet, without computing it (so a lazy ``if`` can tell that its untaken
  branch has a value without evaluating it).

A pure lifted node's value is a function of its operands' held values, so it needs no
state and, once it has a value, ticks on every tick (``cur is held``). The nodes with
state (``when``, ``latch``, ``update``, ``timeout``, aggregates, ``eval``) are
:class:`StatefulNode`: the monitor calls their ``update()`` once per tick before the
stream that contains them is computed.

Streams are :class:`Stream` slots (``cur``, ``held`` and a bounded history of held values);
the monitor (:mod:`trust_checker.monitor`) orders them and steps them. Nodes can be
inspected between ticks: ``node.value()`` is the node's held value at the last tick.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from typing import Final, cast

from trust_checker import operators as op
from trust_checker.errors import SpecError
from trust_checker.lang import ast
from trust_checker.lang.parser import parse_expr
from trust_checker.operators import Fault, Mismatch
from trust_checker.values import BOTTOM, INT_MAX, INT_MIN, NOVAL, MapV, StructV, TupleV, console

__all__ = [
    "INF",
    "Clock",
    "Compiler",
    "EvalNode",
    "Node",
    "StatefulNode",
    "Stream",
    "VarNode",
]

INF: Final = 1 << 62
"""An unbounded number of drain ticks (a literal's ``extra``)."""

Thunk = Callable[[], object]


class Clock:
    """The current tick's timestamp (ns), shared by the real-time nodes."""

    __slots__ = ("ts",)

    def __init__(self) -> None:
        self.ts: int | None = None


class Stream:
    """One stream's state: value at this tick, held value, history of held values
    (``hist[-k]`` is the held value k ticks ago; NoVal there: none yet)."""

    __slots__ = ("cur", "decl", "extra", "held", "hidden", "hist", "kind", "name")

    def __init__(self, name: str, kind: str, decl: ast.Decl | None, *, hidden: bool = False):
        self.name = name
        self.kind = kind
        self.decl = decl
        self.hidden = hidden
        self.cur: object = NOVAL
        self.held: object = NOVAL
        self.hist: deque[object] | None = None
        self.extra = 0

    def __repr__(self) -> str:
        return f"Stream({self.name!r}, cur={self.cur!r}, held={self.held!r})"


class Node:
    """A compiled expression node (see the module docstring)."""

    __slots__ = ("ast", "children", "cur", "held", "started")

    def __init__(
        self,
        node: ast.Expr,
        children: Sequence[Node],
        held: Thunk,
        cur: Thunk | None = None,
        started: Callable[[], bool] | None = None,
    ) -> None:
        self.ast = node
        self.children = tuple(children)
        self.held = held
        self.cur = held if cur is None else cur
        self.started = started

    def value(self) -> object:
        """The held value at the last tick (recomputed; call between ticks)."""
        return self.held()


class VarNode(Node):
    """A bare stream reference (operators read ``stream.held`` directly)."""

    __slots__ = ("stream",)

    def __init__(self, node: ast.Var, stream: Stream) -> None:
        def held() -> object:
            return stream.held

        def cur() -> object:
            return stream.cur

        def started() -> bool:
            return stream.held is not NOVAL

        super().__init__(node, (), held, cur, started)
        self.stream = stream


class StatefulNode(Node):
    """A node with state, updated once per tick by the monitor (``update``)."""

    __slots__ = ("cur_v", "held_v")

    def __init__(self, node: ast.Expr, children: Sequence[Node], *, always: bool) -> None:
        self.cur_v: object = NOVAL
        self.held_v: object = NOVAL
        me = self

        def held() -> object:
            return me.held_v

        def cur() -> object:
            return me.cur_v

        def started() -> bool:
            return me.held_v is not NOVAL

        super().__init__(node, children, held, cur, None if always else started)

    def update(self) -> None:
        raise NotImplementedError

    def _set(self, v: object) -> None:
        self.cur_v = v
        if v is not NOVAL:
            self.held_v = v

    def export(self) -> object:
        """The state to carry over a hot swap (see :meth:`restore`)."""
        return (self.cur_v, self.held_v)

    def restore(self, state: object) -> None:
        self.cur_v, self.held_v = state  # type: ignore[misc]


def _located(f: Fault, where: str) -> Fault:
    if not f.where:
        f.where = where
    return f


# -- pure lifted nodes ----------------------------------------------------------------------


def _all_started(kids: Sequence[Node]) -> Callable[[], bool] | None:
    checks = [k.started for k in kids if k.started is not None]
    if not checks:
        return None
    done = [False]

    def started() -> bool:
        if done[0]:
            return True
        for c in checks:
            if not c():
                return False
        done[0] = True
        return True

    return started


def _lift1(node: ast.Expr, kid: Node, fn: Callable[[object], object], where: str) -> Node:
    fa = kid.held

    def held() -> object:
        a = fa()
        if a is NOVAL or a is BOTTOM:
            return a
        try:
            return fn(a)
        except Fault as e:
            raise _located(e, where) from None

    return Node(node, (kid,), held, None, _all_started((kid,)))


def _lift2(
    node: ast.Expr, ka: Node, kb: Node, fn: Callable[[object, object], object], where: str
) -> Node:
    """A lifted binary node; operands that are stream names or literals are read in place
    (no call), the common case on the hot path."""
    fa, fb = ka.held, kb.held
    kids = (ka, kb)
    if isinstance(kb.ast, ast.Lit):
        c = kb.held()
        if isinstance(ka, VarNode):
            sa = ka.stream

            def held_vc() -> object:
                a = sa.held
                if a is NOVAL or a is BOTTOM:
                    return a
                try:
                    return fn(a, c)
                except Fault as e:
                    raise _located(e, where) from None

            return Node(node, kids, held_vc, None, ka.started)

        def held_c() -> object:
            a = fa()
            if a is NOVAL or a is BOTTOM:
                return a
            try:
                return fn(a, c)
            except Fault as e:
                raise _located(e, where) from None

        return Node(node, kids, held_c, None, ka.started)
    if isinstance(ka, VarNode) and isinstance(kb, VarNode):
        sa, sb = ka.stream, kb.stream

        def held_vv() -> object:
            a = sa.held
            b = sb.held
            if a is NOVAL or b is NOVAL:
                return NOVAL
            if a is BOTTOM or b is BOTTOM:
                return BOTTOM
            try:
                return fn(a, b)
            except Fault as e:
                raise _located(e, where) from None

        return Node(node, kids, held_vv, None, _all_started(kids))

    def held() -> object:
        a = fa()
        b = fb()
        if a is NOVAL or b is NOVAL:
            return NOVAL
        if a is BOTTOM or b is BOTTOM:
            return BOTTOM
        try:
            return fn(a, b)
        except Fault as e:
            raise _located(e, where) from None

    return Node(node, kids, held, None, _all_started(kids))


def _liftn(node: ast.Expr, kids: Sequence[Node], fn: Callable[..., object], where: str) -> Node:
    fs = [k.held for k in kids]

    def held() -> object:
        vals = [f() for f in fs]
        if NOVAL in vals:  # identity first: the markers define no __eq__
            return NOVAL
        if BOTTOM in vals:
            return BOTTOM
        try:
            return fn(*vals)
        except Fault as e:
            raise _located(e, where) from None

    return Node(node, kids, held, None, _all_started(kids))


def _const(node: ast.Expr, v: object) -> Node:
    def held() -> object:
        return v

    return Node(node, (), held)


# -- stateful built-ins ---------------------------------------------------------------------


class _When(StatefulNode):
    __slots__ = ("_fe",)

    def __init__(self, node: ast.Expr, e: Node) -> None:
        super().__init__(node, (e,), always=True)
        self._fe = e.held
        self.cur_v = self.held_v = False

    def update(self) -> None:
        if self.held_v is False:
            v = self._fe()
            if v is not NOVAL and v is not BOTTOM:
                self.cur_v = self.held_v = True


class _Latch(StatefulNode):
    __slots__ = ("_fx", "_fy")

    def __init__(self, node: ast.Expr, x: Node, y: Node) -> None:
        super().__init__(node, (x, y), always=False)
        self._fx, self._fy = x.held, y.cur

    def update(self) -> None:
        if self._fy() is NOVAL:
            self.cur_v = NOVAL
        else:
            self._set(self._fx())


class _Update(StatefulNode):
    __slots__ = ("_fa", "_fb", "_switched")

    def __init__(self, node: ast.Expr, a: Node, b: Node) -> None:
        super().__init__(node, (a, b), always=False)
        self._fa, self._fb = a.held, b.held
        self._switched = False

    def update(self) -> None:
        if not self._switched:
            v = self._fb()
            if v is not NOVAL and v is not BOTTOM:
                self._switched = True
        self._set(self._fb() if self._switched else self._fa())

    def export(self) -> object:
        return (self.cur_v, self.held_v, self._switched)

    def restore(self, state: object) -> None:
        self.cur_v, self.held_v, self._switched = state  # type: ignore[misc]


class _Timeout(StatefulNode):
    __slots__ = ("_clock", "_fx", "_limit", "_since", "_where")

    def __init__(self, node: ast.Expr, x: Node, limit_ns: int, clock: Clock, where: str):
        super().__init__(node, (x,), always=True)
        self._fx, self._limit, self._clock, self._where = x.cur, limit_ns, clock, where
        self._since: int | None = None

    def update(self) -> None:
        now = self._clock.ts
        if now is None:
            raise Fault(
                "timeout(...) needs tick timestamps, and this tick has none "
                "(pass ts_ns to Monitor.step)",
                self._where,
            )
        v = self._fx()
        if self._since is None or (v is not NOVAL and v is not BOTTOM):
            self._since = now
        self.cur_v = self.held_v = now - self._since > self._limit

    def export(self) -> object:
        return (self.cur_v, self.held_v, self._since)

    def restore(self, state: object) -> None:
        self.cur_v, self.held_v, self._since = state  # type: ignore[misc]


class _Aggregate(StatefulNode):
    """``x.aggregate(over: W, using: f)`` over the data values x took at ticks whose
    timestamp is within ``(now - W, now]``; bounded by ``cap`` samples."""

    __slots__ = (
        "_cap",
        "_clock",
        "_floats",
        "_fx",
        "_isum",
        "_mono",
        "_q",
        "_using",
        "_where",
        "_window",
    )

    def __init__(self, node: ast.Aggregate, x: Node, clock: Clock, cap: int, where: str) -> None:
        super().__init__(node, (x,), always=True)
        self._fx, self._clock, self._cap, self._where = x.cur, clock, cap, where
        self._window, self._using = node.window_ns, node.using
        self._q: deque[tuple[int, object]] = deque()
        self._mono: deque[tuple[int, object]] = deque()
        self._isum = 0
        self._floats = 0

    def update(self) -> None:
        now = self._clock.ts
        if now is None:
            raise Fault(
                f"x.aggregate(using: {self._using}) needs tick timestamps, and this tick "
                "has none (pass ts_ns to Monitor.step)",
                self._where,
            )
        v = self._fx()
        using = self._using
        if v is not NOVAL and v is not BOTTOM:
            if using != "count" and (type(v) is not int and type(v) is not float):
                raise Fault(f"aggregate {using} needs numbers, got {console(v)}", self._where)
            if len(self._q) >= self._cap:
                raise Fault(
                    f"aggregate window holds more than {self._cap} samples "
                    "(raise Limits.window_samples or shorten the window)",
                    self._where,
                )
            self._q.append((now, v))
            if type(v) is int:
                self._isum += v
            else:
                self._floats += 1
            if using in ("min", "max"):
                mono = self._mono
                if using == "min":
                    while mono and mono[-1][1] >= v:  # type: ignore[operator]
                        mono.pop()
                else:
                    while mono and mono[-1][1] <= v:  # type: ignore[operator]
                        mono.pop()
                mono.append((now, v))
        edge = now - self._window
        q = self._q
        while q and q[0][0] <= edge:
            _, old = q.popleft()
            if type(old) is int:
                self._isum -= old
            else:
                self._floats -= 1
        while self._mono and self._mono[0][0] <= edge:
            self._mono.popleft()
        self.cur_v = self.held_v = self._fold()

    def _fold(self) -> object:
        n = len(self._q)
        if self._using == "count":
            return n
        if self._using in ("min", "max"):
            return self._mono[0][1] if self._mono else BOTTOM
        if self._floats:
            total: object = math.fsum(v for _, v in self._q)  # type: ignore[misc]
        else:
            if not INT_MIN <= self._isum <= INT_MAX:
                raise Fault(
                    f"Int overflow: the window's sum {self._isum} does not fit in 64 bits",
                    self._where,
                )
            total = self._isum
        if self._using == "sum":
            return total
        return total / n if n else BOTTOM  # type: ignore[operator]

    def export(self) -> object:
        return (self.cur_v, self.held_v, list(self._q), list(self._mono))

    def restore(self, state: object) -> None:
        self.cur_v, self.held_v, q, mono = cast(
            tuple[object, object, list[tuple[int, object]], list[tuple[int, object]]], state
        )
        self._q.clear()
        self._mono.clear()
        self._isum = self._floats = 0
        for t, v in q:
            self._q.append((t, v))
            if type(v) is int:
                self._isum += v
            else:
                self._floats += 1
        self._mono.extend(mono)


# -- the compiler ---------------------------------------------------------------------------


class Compiler:
    """Compiles expressions against a set of streams.

    ``lookup(name)`` gives the stream a name refers to (raising :class:`Fault` for a name
    that cannot be used there); ``hidden(index)`` the stream standing for a non-variable
    operand of ``x[k]``. Stateful nodes are appended to ``stateful`` in post-order, the
    order the monitor updates them in.
    """

    def __init__(
        self,
        *,
        path: str,
        clock: Clock,
        lookup: Callable[[str, ast.Expr, int], Stream],
        hidden: Callable[[ast.Index], Stream],
        make_eval: Callable[[ast.Eval, Node, Compiler], StatefulNode],
        window_samples: int,
    ) -> None:
        self.path = path
        self.clock = clock
        self.lookup = lookup
        self.hidden = hidden
        self.make_eval = make_eval
        self.window_samples = window_samples
        self.stateful: list[StatefulNode] = []

    def where(self, e: ast.Expr) -> str:
        return f"{self.path}:{e.pos}"

    def compile(self, e: ast.Expr) -> Node:
        if isinstance(e, ast.Lit):
            return _const(e, e.value)
        if isinstance(e, ast.Var):
            return self._var(e)
        if isinstance(e, ast.Index):
            return self._index(e)
        if isinstance(e, ast.Binary):
            return _lift2(
                e, self.compile(e.left), self.compile(e.right), op.BINARY[e.op], self.where(e)
            )
        if isinstance(e, ast.Unary):
            fn = op.negate if e.op == "-" else op.logical_not
            return _lift1(e, self.compile(e.operand), fn, self.where(e))
        if isinstance(e, ast.If):
            return self._if(e)
        if isinstance(e, ast.Call):
            return self._call(e)
        if isinstance(e, ast.Field):
            name = e.name
            return _lift1(e, self.compile(e.expr), lambda v: op.field(v, name), self.where(e))
        if isinstance(e, ast.ListLit):
            return self._container(e, e.items, tuple)
        if isinstance(e, ast.TupleLit):
            return self._container(e, e.items, TupleV)
        if isinstance(e, ast.MapLit | ast.StructLit):
            pairs = e.pairs if isinstance(e, ast.MapLit) else e.fields
            keys = [k for k, _ in pairs]
            cls = MapV if isinstance(e, ast.MapLit) else StructV
            return self._container(
                e, [x for _, x in pairs], lambda vals: cls(zip(keys, vals, strict=True))
            )
        if isinstance(e, ast.Aggregate):
            x = self.compile(e.expr)
            return self._stateful(_Aggregate(e, x, self.clock, self.window_samples, self.where(e)))
        if isinstance(e, ast.Eval):
            source = self.compile(e.source)
            return self._stateful(self.make_eval(e, source, self))
        raise Fault(f"cannot evaluate {type(e).__name__} nodes", self.where(e))

    def _stateful(self, n: StatefulNode) -> StatefulNode:
        self.stateful.append(n)
        return n

    def _var(self, e: ast.Var) -> Node:
        return VarNode(e, self.lookup(e.name, e, 0))

    def _index(self, e: ast.Index) -> Node:
        if isinstance(e.expr, ast.Var):
            s = self.lookup(e.expr.name, e, e.offset)
            kid = self._var(e.expr) if e.offset == 0 else _const(e.expr, NOVAL)
        else:
            s = self.hidden(e)
            kid = _const(e.expr, NOVAL)
        k = e.offset
        if k == 0:

            def held0() -> object:
                v = s.held
                return BOTTOM if v is NOVAL else v

            return Node(e, (kid,), held0)
        hist = s.hist
        if hist is None or (hist.maxlen or 0) < k:
            raise Fault(
                f"{s.name}[{k}] reaches further back than the {hist.maxlen if hist else 0} "
                "ticks of history kept (raise Limits.dynamic_history)",
                self.where(e),
            )
        neg = -k

        def held() -> object:
            v = hist[neg]
            return BOTTOM if v is NOVAL else v

        return Node(e, (kid,), held)

    def _container(
        self, e: ast.Expr, items: Sequence[ast.Expr], build: Callable[[list[object]], object]
    ) -> Node:
        kids = [self.compile(x) for x in items]
        if not kids:
            return _const(e, build([]))
        return _liftn(e, kids, lambda *vals: build(list(vals)), self.where(e))

    def _if(self, e: ast.If) -> Node:
        kc, ka, kb = self.compile(e.cond), self.compile(e.then), self.compile(e.else_)
        fc, fa, fb = kc.held, ka.held, kb.held
        started = _all_started((kc, ka, kb))
        where = self.where(e)

        ok = [started is None]

        def held() -> object:
            if not ok[0]:
                if not started():  # type: ignore[misc]
                    return NOVAL
                ok[0] = True
            c = fc()
            if c is True:
                return fa()
            if c is False:
                return fb()
            if c is BOTTOM:
                return BOTTOM
            raise Fault(f"the condition of 'if' must be a Bool, got {console(c)}", where)

        return Node(e, (kc, ka, kb), held, None, started)

    def _call(self, e: ast.Call) -> Node:
        f = e.func
        where = self.where(e)
        if f in op.CALLS:
            arity, fn = op.CALLS[f]
            self._arity(e, arity)
            kids = [self.compile(a) for a in e.args]
            if arity == 1:
                return _lift1(e, kids[0], fn, where)
            if arity == 2:
                return _lift2(e, kids[0], kids[1], fn, where)
            return _liftn(e, kids, fn, where)
        if f == "timeout":
            self._arity(e, 2)
            limit = e.args[1]
            if not isinstance(limit, ast.Lit) or type(limit.value) is not int:
                raise Fault("timeout(x, d) needs a duration literal for d, e.g. 2s", where)
            x = self.compile(e.args[0])
            return self._stateful(_Timeout(e, x, limit.value, self.clock, where))
        if f not in ("default", "init", "is_defined", "when", "latch", "update"):
            raise Fault(f"unknown function '{f}'", where)
        self._arity(e, 1 if f in ("is_defined", "when") else 2)
        kids = [self.compile(a) for a in e.args]
        if f == "when":
            return self._stateful(_When(e, kids[0]))
        if f == "latch":
            return self._stateful(_Latch(e, kids[0], kids[1]))
        if f == "update":
            return self._stateful(_Update(e, kids[0], kids[1]))
        if f == "is_defined":
            fe = kids[0].held

            def held_def() -> object:
                v = fe()
                return NOVAL if v is NOVAL else v is not BOTTOM

            return Node(e, kids, held_def, None, kids[0].started)
        if f == "default":
            return self._default(e, kids[0], kids[1])
        return self._init(e, kids[0], kids[1])

    def _arity(self, e: ast.Call, n: int) -> None:
        if len(e.args) != n:
            raise Fault(
                f"{e.func} takes {n} argument{'s' if n != 1 else ''}, got {len(e.args)}",
                self.where(e),
            )

    @staticmethod
    def _default(e: ast.Call, ke: Node, kd: Node) -> Node:
        fe, fd, sd = ke.held, kd.held, kd.started

        def held() -> object:
            v = fe()
            if v is NOVAL:
                return NOVAL
            if v is BOTTOM:
                return fd()
            if sd is not None and not sd():
                return NOVAL
            return v

        return Node(e, (ke, kd), held, None, _all_started((ke, kd)))

    @staticmethod
    def _init(e: ast.Call, ke: Node, kd: Node) -> Node:
        eh, ec, dh = ke.held, ke.cur, kd.held

        def held() -> object:
            v = eh()
            return dh() if v is NOVAL else v

        if ec is eh:
            cur = held
        else:

            def cur() -> object:
                return dh() if eh() is NOVAL else ec()

        se, sd = ke.started, kd.started
        if se is None or sd is None:
            started = None
        else:

            def started() -> bool:
                return se() or sd()

        return Node(e, (ke, kd), held, cur, started)


# -- eval / dynamic / defer ------------------------------------------------------------------


class EvalNode(StatefulNode):
    """``eval(s)`` / ``dynamic(s)`` and ``defer(s)``: the expression held in the Str stream
    ``s``, parsed with the checker's own parser and compiled by ``compiler()`` (whose
    ``lookup`` enforces the scope). ``eval`` re-parses whenever the text changes; ``defer``
    keeps the first expression that parses."""

    __slots__ = ("_compiler", "_conform", "_expr", "_fixed", "_src", "_text", "_updates", "_where")

    def __init__(
        self,
        node: ast.Eval,
        source: Node,
        compiler: Callable[[], Compiler],
        where: str,
    ) -> None:
        super().__init__(node, (source,), always=False)
        self._src = source.held
        self._compiler = compiler
        self._where = where
        self._conform = None if node.ascription is None else op.conformer(node.ascription)
        self._text: str | None = None
        self._expr: Node | None = None
        self._updates: list[StatefulNode] = []
        self._fixed = False

    @property
    def kind(self) -> str:
        return self.ast.kind  # type: ignore[union-attr]

    def update(self) -> None:
        s = self._src()
        if s is NOVAL:
            self.cur_v = NOVAL
            return
        if not self._fixed:
            if s is BOTTOM:
                self._set(BOTTOM)
                return
            if type(s) is not str:
                raise Fault(
                    f"{self.kind}(s) needs a Str holding an expression, got {console(s)}",
                    self._where,
                )
            if s != self._text:
                self._load(s)
        if self._expr is None:
            self._set(BOTTOM)
            return
        for u in self._updates:
            u.update()
        v = self._expr.cur()
        if self._conform is not None and v is not NOVAL:
            try:
                v = self._conform(v)
            except Mismatch as m:
                raise Fault(
                    f"{self.kind} of {self._text!r} gave a value of the wrong type: {m} "
                    "(fix the expression or the ascription)",
                    self._where,
                ) from None
        self._set(v)

    def _load(self, text: str) -> None:
        self._text = text
        self._expr = None
        self._updates = []
        try:
            tree = parse_expr(text, f"<{self.kind} at {self._where}>")
            c = self._compiler()
            expr = c.compile(tree)
        except SpecError as e:
            raise Fault(
                f"cannot parse the {self.kind} expression {text!r}: {e}", self._where
            ) from None
        except Fault as f:
            raise Fault(
                f"cannot use the {self.kind} expression {text!r}: {f.message}"
                + (f" ({f.where})" if f.where else ""),
                self._where,
            ) from None
        self._expr, self._updates = expr, c.stateful
        self._fixed = self.kind == "defer"

    def export(self) -> object:
        inner = [u.export() for u in self._updates]
        return (self.cur_v, self.held_v, self._text, self._fixed, inner)

    def restore(self, state: object) -> None:
        self.cur_v, self.held_v, text, fixed, inner = cast(
            tuple[object, object, str | None, bool, list[object]], state
        )
        if text is None:
            return
        try:
            self._load(text)
        except Fault:
            return
        self._fixed = fixed
        if len(inner) == len(self._updates):
            for u, st in zip(self._updates, inner, strict=True):
                u.restore(st)
