"""Compiling expressions into closures (no Python source, no ``compile``/``exec``): each
AST node becomes an :class:`~.nodes.ExprNode` (see :mod:`.nodes` for the model,
:mod:`.lifted` for the operators, :mod:`.stateful` and :mod:`.dynamic` for the nodes with
state).

Speed (measured in bench/trust), with the semantics unchanged: a pure operator over
constants is folded into a :class:`~.nodes.ConstNode` when compiled (``Map("a": 1)`` is
built once, not on every tick); an ``if`` computes a comparison condition in place, and
a chain ``if x == "a" then 1 else if x == "b" then 2 else 0`` is a table lookup.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Final

from trust_checker import operators as op
from trust_checker.engine.lifted import (
    FAST1,
    FAST2,
    FAST_CALL1,
    FAST_CALL2,
    lift1,
    lift2,
    liftn,
    map_get_ss,
)
from trust_checker.engine.nodes import (
    ConstNode,
    ExprNode,
    StatefulNode,
    Stream,
    Thunk,
    TickTime,
    VarNode,
    all_started,
    const,
    type_hint,
    value_hint,
)
from trust_checker.engine.stateful import (
    AggregateNode,
    LatchNode,
    TimeoutNode,
    UpdateNode,
    WhenNode,
)
from trust_checker.lang import ast
from trust_checker.operators import Fault
from trust_checker.values import BOTTOM, NOVAL, MapV, StructV, TupleV, console

__all__ = ["Compiler"]


def _switch(e: ast.If) -> tuple[str, type, dict[object, object], object] | None:
    """A chain ``if x == k1 then r1 else if x == k2 then r2 ... else r`` on one stream
    ``x``, with literal keys of one type (Str or Int) and literal results, as a table:
    for a value of the keys' type the chain's value is the first ki's ri, else r (x's
    other values, NoVal and ⊥ take the chain itself)."""
    name: str | None = None
    kt: type | None = None
    cases: dict[object, object] = {}
    x: ast.Expr = e
    while isinstance(x, ast.If):
        c = x.cond
        if not (isinstance(c, ast.Binary) and c.op == "==" and isinstance(x.then, ast.Lit)):
            return None
        var, key = (c.left, c.right) if isinstance(c.left, ast.Var) else (c.right, c.left)
        if not isinstance(var, ast.Var) or not isinstance(key, ast.Lit):
            return None
        if name is None:
            name, kt = var.name, type(key.value)
        if var.name != name or type(key.value) is not kt or kt not in (str, int):
            return None
        cases.setdefault(key.value, x.then.value)
        x = x.else_
    if not isinstance(x, ast.Lit) or name is None or kt is None or len(cases) < 2:
        return None
    return name, kt, cases, x.value


_FOLDABLE: Final = (
    ast.Binary,
    ast.Unary,
    ast.If,
    ast.Call,
    ast.Field,
    ast.ListLit,
    ast.TupleLit,
    ast.MapLit,
    ast.StructLit,
)
"""Pure lifted operators: over constant operands, a constant."""
_PURE_CALLS: Final = frozenset(op.CALLS) | {"default", "is_defined"}


class Compiler:
    """Compiles expressions against a set of streams.

    ``lookup(name)`` gives the stream a name refers to (raising :class:`Fault` for a name
    that cannot be used there); ``hidden(index)`` the stream standing for a non-variable
    operand of ``x[k]``. Stateful nodes are appended to ``stateful`` in post-order, the
    order the runner updates them in.
    """

    def __init__(
        self,
        *,
        path: str,
        clock: TickTime,
        lookup: Callable[[str, ast.Expr, int], Stream],
        hidden: Callable[[ast.Index], Stream],
        make_eval: Callable[[ast.Eval, ExprNode, Compiler], StatefulNode],
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

    def compile(self, e: ast.Expr) -> ExprNode:
        n = self._compile(e)
        if (
            n.children
            and isinstance(e, _FOLDABLE)
            and all(isinstance(k, ConstNode) for k in n.children)
            and not (isinstance(e, ast.Call) and e.func not in _PURE_CALLS)
        ):
            # a pure operator over constants: the same value on every tick, computed
            # once here (a run-time error stays one, raised at its tick with its stream)
            try:
                return ConstNode(e, n.children, n.held())
            except (Fault, TypeError, ValueError, ArithmeticError):
                return n
        return n

    def _compile(self, e: ast.Expr) -> ExprNode:
        if isinstance(e, ast.Lit):
            return const(e, e.value)
        if isinstance(e, ast.Var):
            return self._var(e)
        if isinstance(e, ast.Index):
            return self._index(e)
        if isinstance(e, ast.Binary):
            ka, kb = self.compile(e.left), self.compile(e.right)
            fast = FAST2.get((e.op, ka.hint, kb.hint))  # type: ignore[arg-type]
            return lift2(e, ka, kb, op.BINARY[e.op], self.where(e), fast)
        if isinstance(e, ast.Unary):
            fn = op.negate if e.op == "-" else op.logical_not
            k = self.compile(e.operand)
            fast1 = FAST1.get((e.op, k.hint))  # type: ignore[arg-type]
            return lift1(e, k, fn, self.where(e), fast1)
        if isinstance(e, ast.If):
            return self._if(e)
        if isinstance(e, ast.Call):
            return self._call(e)
        if isinstance(e, ast.Field):
            name = e.name
            return lift1(e, self.compile(e.expr), lambda v: op.field(v, name), self.where(e))
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
            return self._stateful(
                AggregateNode(e, x, self.clock, self.window_samples, self.where(e))
            )
        if isinstance(e, ast.Eval):
            source = self.compile(e.source)
            return self._stateful(self.make_eval(e, source, self))
        raise Fault(f"cannot evaluate {type(e).__name__} nodes", self.where(e))

    def _stateful(self, n: StatefulNode) -> StatefulNode:
        self.stateful.append(n)
        return n

    def _var(self, e: ast.Var) -> ExprNode:
        return VarNode(e, self.lookup(e.name, e, 0))

    def _index(self, e: ast.Index) -> ExprNode:
        if isinstance(e.expr, ast.Var):
            s = self.lookup(e.expr.name, e, e.offset)
            kid = self._var(e.expr) if e.offset == 0 else const(e.expr, NOVAL)
        else:
            s = self.hidden(e)
            kid = const(e.expr, NOVAL)
        k = e.offset
        hint = type_hint(s.decl)
        if k == 0:

            def held0() -> object:
                v = s.held
                return BOTTOM if v is NOVAL else v

            return ExprNode(e, (kid,), held0, None, None, hint)
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

        return ExprNode(e, (kid,), held, None, None, hint)

    def _container(
        self, e: ast.Expr, items: Sequence[ast.Expr], build: Callable[[list[object]], object]
    ) -> ExprNode:
        kids = [self.compile(x) for x in items]
        if not kids:
            return const(e, build([]))
        return liftn(e, kids, lambda *vals: build(list(vals)), self.where(e))

    def _if(self, e: ast.If) -> ExprNode:
        kc, ka, kb = self.compile(e.cond), self.compile(e.then), self.compile(e.else_)
        fc, fa, fb = kc.held, ka.held, kb.held
        sc, sa, sb = kc.src, ka.src, kb.src
        started = all_started((kc, ka, kb))
        where = self.where(e)
        ok = started is None

        def bad(c: object) -> object:
            if c is BOTTOM:
                return BOTTOM
            raise Fault(f"the condition of 'if' must be a Bool, got {console(c)}", where)

        held: Thunk
        if kc.fused is not None:
            pyop, sx, sy, tx, ty = kc.fused

            def held() -> object:
                nonlocal ok
                if not ok:
                    if not started():  # type: ignore[misc]
                        return NOVAL
                    ok = True
                x = sx.held
                y = sy.held
                c = pyop(x, y) if type(x) is tx and type(y) is ty else fc()
                if c is True:
                    return fa() if sa is None else sa.held
                if c is False:
                    return fb() if sb is None else sb.held
                return bad(c)

        elif sc is not None:

            def held() -> object:
                nonlocal ok
                if not ok:
                    if not started():  # type: ignore[misc]
                        return NOVAL
                    ok = True
                c = sc.held
                if c is True:
                    return fa() if sa is None else sa.held
                if c is False:
                    return fb() if sb is None else sb.held
                return bad(c)

        else:

            def held() -> object:
                nonlocal ok
                if not ok:
                    if not started():  # type: ignore[misc]
                        return NOVAL
                    ok = True
                c = fc()
                if c is True:
                    return fa() if sa is None else sa.held
                if c is False:
                    return fb() if sb is None else sb.held
                return bad(c)

        hint = ka.hint if ka.hint is kb.hint else None
        table = _switch(e)
        if table is not None:  # if x == "a" then 1 else if x == "b" then 2 else 0
            name, kt, cases, other = table
            sx = self.lookup(name, e, 0)
            general = held

            def held() -> object:
                v = sx.held
                if type(v) is kt:
                    return cases.get(v, other)
                return general()

        return ExprNode(e, (kc, ka, kb), held, None, started, hint)

    def _call(self, e: ast.Call) -> ExprNode:
        f = e.func
        where = self.where(e)
        if f in op.CALLS:
            arity, fn = op.CALLS[f]
            self._arity(e, arity)
            kids = [self.compile(a) for a in e.args]
            if arity == 1:
                fast1 = FAST_CALL1.get((f, kids[0].hint))  # type: ignore[arg-type]
                if fast1 is not None and f == "List.head":
                    fast1 = (fast1[0], False, value_hint(kids[0]))
                return lift1(e, kids[0], fn, where, fast1)
            if arity == 2:
                fast = FAST_CALL2.get((f, kids[0].hint, kids[1].hint))  # type: ignore[arg-type]
                if fast is not None and f == "Map.get":
                    if kids[0].src is not None and kids[1].src is not None:
                        return map_get_ss(e, kids[0], kids[1], where)
                    fast = (fast[0], False, value_hint(kids[0]))
                return lift2(e, kids[0], kids[1], fn, where, fast)
            return liftn(e, kids, fn, where)
        if f == "timeout":
            self._arity(e, 2)
            limit = e.args[1]
            if not isinstance(limit, ast.Lit) or type(limit.value) is not int:
                raise Fault("timeout(x, d) needs a duration literal for d, e.g. 2s", where)
            x = self.compile(e.args[0])
            return self._stateful(TimeoutNode(e, x, limit.value, self.clock, where))
        if f not in ("default", "init", "is_defined", "when", "latch", "update"):
            raise Fault(f"unknown function '{f}'", where)
        self._arity(e, 1 if f in ("is_defined", "when") else 2)
        kids = [self.compile(a) for a in e.args]
        if f == "when":
            return self._stateful(WhenNode(e, kids[0]))
        if f == "latch":
            return self._stateful(LatchNode(e, kids[0], kids[1]))
        if f == "update":
            return self._stateful(UpdateNode(e, kids[0], kids[1]))
        if f == "is_defined":
            fe = kids[0].held

            def held_def() -> object:
                v = fe()
                return NOVAL if v is NOVAL else v is not BOTTOM

            return ExprNode(e, kids, held_def, None, kids[0].started, bool)
        if f == "default":
            past = e.args[0]
            if (
                isinstance(past, ast.Index)
                and isinstance(past.expr, ast.Var)
                and past.offset > 0
                and isinstance(kids[1], ConstNode)
            ):  # x[k] with a constant default (D5.2's x[-k, c]): read the history here
                return self._default_past(e, kids[0], kids[1], past, past.expr.name)
            return self._default(e, kids[0], kids[1])
        return self._init(e, kids[0], kids[1])

    def _default_past(
        self, e: ast.Call, ke: ExprNode, kd: ConstNode, past: ast.Index, name: str
    ) -> ExprNode:
        hist = self.lookup(name, past, past.offset).hist
        assert hist is not None  # the index node compiled: it has this much history
        neg, d = -past.offset, kd.const

        def held() -> object:
            v = hist[neg]
            if v is NOVAL or v is BOTTOM:
                return d
            return v

        hint = ke.hint if ke.hint is kd.hint else None
        return ExprNode(e, (ke, kd), held, None, None, hint)

    def _arity(self, e: ast.Call, n: int) -> None:
        if len(e.args) != n:
            raise Fault(
                f"{e.func} takes {n} argument{'s' if n != 1 else ''}, got {len(e.args)}",
                self.where(e),
            )

    @staticmethod
    def _default(e: ast.Call, ke: ExprNode, kd: ExprNode) -> ExprNode:
        fe, fd, sd = ke.held, kd.held, kd.started
        src_d = kd.src
        held: Thunk
        if sd is None and src_d is not None:  # the common default(x[k], literal)

            def held() -> object:
                v = fe()
                if v is BOTTOM:
                    return src_d.held
                return v

        else:

            def held() -> object:
                v = fe()
                if v is NOVAL:
                    return NOVAL
                if v is BOTTOM:
                    return fd()
                if sd is not None and not sd():
                    return NOVAL
                return v

        hint = ke.hint if ke.hint is kd.hint else None
        return ExprNode(e, (ke, kd), held, None, all_started((ke, kd)), hint)

    @staticmethod
    def _init(e: ast.Call, ke: ExprNode, kd: ExprNode) -> ExprNode:
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

        return ExprNode(e, (ke, kd), held, cur, started)
