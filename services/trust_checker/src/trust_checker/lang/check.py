"""Static checks of a parsed spec, before it may run.

:func:`check_spec` returns every problem found (an empty list: the spec may run):

- declarations and equations: each ``out``/``aux`` has exactly one equation, inputs none,
  no equation or use of an undeclared name, no stream declared twice;
- functions: known built-ins with the right number of arguments;
- types, gradually: declared and literal types flow through the operators; a stream
  without a declared type, or of type ``Any``, is unknown and passes (the runner checks
  its values at run time);
- no zero-weight dependency cycle (streams that need each other at the same tick);
- the memory bound (:func:`memory_bound`) within :attr:`Limits.max_history_slots`.

:func:`dependency_order` gives the order the evaluator computes streams in.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Final

from trust_checker.errors import Problem, SpecError
from trust_checker.lang import ast
from trust_checker.lang.lexer import source_line
from trust_checker.values import UNIT

__all__ = ["Limits", "check_spec", "children", "dependency_order", "memory_bound"]


@dataclass(frozen=True, slots=True)
class Limits:
    max_history_slots: int = 1_000_000
    """The most history slots (one per stored past value) a spec may need."""
    dynamic_history: int = 64
    """Past values kept for every stream when the spec uses ``eval``/``defer`` (whose
    expressions, unknown in advance, may read ``x[k]``)."""
    window_samples: int = 10_000
    """Samples one ``x.aggregate(...)`` window may hold."""


_SIGNATURES: Final[dict[str, str]] = {
    "default": "default(e, d)",
    "init": "init(e, d)",
    "is_defined": "is_defined(e)",
    "when": "when(e)",
    "latch": "latch(x, y)",
    "update": "update(a, b)",
    "sin": "sin(x)",
    "cos": "cos(x)",
    "tan": "tan(x)",
    "abs": "abs(x)",
    "List.get": "List.get(list, index)",
    "List.concat": "List.concat(a, b)",
    "List.append": "List.append(list, item)",
    "List.head": "List.head(list)",
    "List.tail": "List.tail(list)",
    "List.len": "List.len(list)",
    "Map.get": "Map.get(map, key)",
    "Map.insert": "Map.insert(map, key, value)",
    "Map.remove": "Map.remove(map, key)",
    "Map.has_key": "Map.has_key(map, key)",
    "timeout": "timeout(x, 2s)",
}
_ARITY: Final = {f: sig.count(",") + 1 for f, sig in _SIGNATURES.items()}
_CALLABLE: Final = sorted({*_SIGNATURES, "eval", "dynamic", "defer", "List", "Map", "Struct"})

INT: Final = ast.TName("Int")
FLOAT: Final = ast.TName("Float")
STR: Final = ast.TName("Str")
BOOL: Final = ast.TName("Bool")
_NUMERIC: Final = (INT, FLOAT)

Ty = ast.Type | None
"""A type, or None: unknown (checked at run time)."""


def children(e: ast.Expr) -> Iterator[ast.Expr]:
    """The direct sub-expressions of ``e`` (for ``eval``/``defer``: its source only)."""
    match e:
        case ast.Index(expr=x) | ast.Unary(operand=x) | ast.Field(expr=x):
            yield x
        case ast.Aggregate(expr=x) | ast.Eval(source=x):
            yield x
        case ast.Binary(left=a, right=b):
            yield a
            yield b
        case ast.If(cond=c, then=a, else_=b):
            yield from (c, a, b)
        case ast.Call(args=xs) | ast.ListLit(items=xs) | ast.TupleLit(items=xs):
            yield from xs
        case ast.MapLit(pairs=ps) | ast.StructLit(fields=ps):
            yield from (x for _, x in ps)
        case _:
            return


@dataclass(frozen=True, slots=True)
class _Ref:
    """A stream read at ``weight`` ticks in the past, at ``pos`` (of the Var)."""

    name: str
    weight: int
    pos: ast.Pos
    index_pos: ast.Pos


def _refs(e: ast.Expr, weight: int = 0, index_pos: ast.Pos = ast.NOWHERE) -> Iterator[_Ref]:
    if isinstance(e, ast.Var):
        yield _Ref(e.name, weight, e.pos, index_pos if weight else e.pos)
        return
    if isinstance(e, ast.Index):
        yield from _refs(e.expr, weight + e.offset, e.pos)
        return
    for c in children(e):
        yield from _refs(c, weight, index_pos)


def _walk(e: ast.Expr) -> Iterator[ast.Expr]:
    yield e
    for c in children(e):
        yield from _walk(c)


def _known(t: Ty) -> ast.Type | None:
    return None if t is None or t == ast.TAny else t


def _compatible(a: Ty, b: Ty, *, numeric_mix: bool = False) -> bool:
    a, b = _known(a), _known(b)
    if a is None or b is None:
        return True
    if numeric_mix and a in _NUMERIC and b in _NUMERIC:
        return True
    match a, b:
        case ast.TName(), ast.TName():
            return a == b
        case ast.TList(elem=x), ast.TList(elem=y):
            return _compatible(x, y, numeric_mix=numeric_mix)
        case ast.TMap(value=x), ast.TMap(value=y):
            return _compatible(x, y, numeric_mix=numeric_mix)
        case ast.TStruct(fields=fx), ast.TStruct(fields=fy):
            return [k for k, _ in fx] == [k for k, _ in fy] and all(
                _compatible(x, y, numeric_mix=numeric_mix)
                for (_, x), (_, y) in zip(fx, fy, strict=True)
            )
        case ast.TTuple(items=xs), ast.TTuple(items=ys):
            return len(xs) == len(ys) and all(
                _compatible(x, y, numeric_mix=numeric_mix) for x, y in zip(xs, ys, strict=True)
            )
    return False


def _name(t: Ty) -> str:
    return "unknown" if t is None else str(t)


class _Checker:
    def __init__(self, spec: ast.Spec, limits: Limits) -> None:
        self.spec = spec
        self.limits = limits
        self.problems: list[Problem] = []
        self.decls: dict[str, ast.Decl] = {}
        for d in spec.decls:
            if d.name in self.decls:
                first = self.decls[d.name].pos
                self.problem(
                    d.pos,
                    f"stream '{d.name}' is declared twice (first at {first})",
                    "remove one of the declarations",
                )
            else:
                self.decls[d.name] = d

    def problem(self, pos: ast.Pos, message: str, hint: str = "") -> None:
        text = source_line(self.spec.source, pos.line)
        self.problems.append(Problem(self.spec.path, pos.line, pos.col, message, text, hint))

    def exprs(self) -> Iterator[ast.Expr]:
        yield from (eq.expr for eq in self.spec.equations)
        yield from (t.cond for t in self.spec.triggers)

    # -- declarations, names, functions ------------------------------------------------

    def equations(self) -> None:
        seen: dict[str, ast.Equation] = {}
        for eq in self.spec.equations:
            d = self.decls.get(eq.name)
            if d is None:
                self.problem(
                    eq.pos,
                    f"equation for '{eq.name}', which is not declared",
                    f"declare it: out {eq.name}: T (or aux {eq.name}: T)",
                )
            elif d.kind == "in":
                self.problem(
                    eq.pos,
                    f"input '{eq.name}' has an equation",
                    "inputs take their values from outside; declare it out or aux to compute it",
                )
            elif eq.name in seen:
                self.problem(
                    eq.pos,
                    f"'{eq.name}' has a second equation (the first is at {seen[eq.name].pos})",
                    "a stream has exactly one equation; combine them with if ... then ... else",
                )
            seen.setdefault(eq.name, eq)
        for d in self.decls.values():
            if d.kind != "in" and d.name not in seen:
                self.problem(
                    d.pos,
                    f"{'output' if d.kind == 'out' else 'aux stream'} '{d.name}' has no equation",
                    f"add one: {d.name} = EXPR",
                )

    def unknown_name(self, name: str, pos: ast.Pos) -> None:
        close = difflib.get_close_matches(name, list(self.decls), n=1)
        hint = f"did you mean '{close[0]}'? Otherwise d" if close else "d"
        self.problem(pos, f"unknown stream '{name}'", hint + f"eclare it: in {name}: T")

    def names_and_calls(self) -> None:
        for root in self.exprs():
            for e in _walk(root):
                if isinstance(e, ast.Var) and e.name not in self.decls:
                    self.unknown_name(e.name, e.pos)
                elif isinstance(e, ast.Eval) and e.scope is not None:
                    for n in e.scope:
                        if n not in self.decls:
                            self.unknown_name(n, e.pos)
                elif isinstance(e, ast.Call):
                    self.call_shape(e)

    def call_shape(self, e: ast.Call) -> bool:
        """Report an unknown function or a wrong arity; True if the call is well formed."""
        if e.func not in _ARITY:
            close = difflib.get_close_matches(e.func, _CALLABLE, n=1)
            hint = f"did you mean {close[0]}? " if close else ""
            hint += "the built-ins are " + ", ".join(_CALLABLE)
            self.problem(e.pos, f"unknown function '{e.func}'", hint)
            return False
        if len(e.args) != _ARITY[e.func]:
            n = _ARITY[e.func]
            self.problem(
                e.pos,
                f"'{e.func}' takes {n} argument{'s' if n > 1 else ''}, found {len(e.args)}",
                f"write {_SIGNATURES[e.func]}",
            )
            return False
        if e.func == "timeout":
            dur = e.args[1]
            if not (isinstance(dur, ast.Lit) and type(dur.value) is int):
                self.problem(dur.pos, "the timeout must be a duration", "write timeout(x, 2s)")
                return False
        return True

    # -- types -----------------------------------------------------------------------------

    def types(self) -> None:
        for eq in self.spec.equations:
            found = self.infer(eq.expr)
            d = self.decls.get(eq.name)
            declared = None if d is None or d.kind == "in" else _known(d.type)
            if declared is not None and found is not None and not _compatible(declared, found):
                hint = "change the declared type or the equation"
                if declared == FLOAT and found == INT:
                    hint = "an Int is not a Float: write Float literals (1.0) or mix in a Float"
                self.problem(
                    eq.expr.pos,
                    f"'{eq.name}' is declared {declared} but its equation gives {found}",
                    hint,
                )
        for t in self.spec.triggers:
            self.expect(t.cond, BOOL, "the condition of a trigger")

    def expect(self, e: ast.Expr, want: ast.Type | tuple[ast.Type, ...], what: str) -> Ty:
        """Infer ``e``; report unless it is unknown or one of ``want``."""
        t = self.infer(e)
        wants = want if isinstance(want, tuple) else (want,)
        if t is not None and not any(_compatible(t, w) for w in wants):
            self.mismatch(e.pos, what, " or ".join(map(str, wants)), t)
            return None
        return t

    def mismatch(self, pos: ast.Pos, what: str, want: str, found: Ty, hint: str = "") -> None:
        self.problem(pos, f"type error: {what} must be {want}, found {_name(found)}", hint)

    def unify(self, a: Ty, b: Ty, pos: ast.Pos, what: str) -> Ty:
        if not _compatible(a, b):
            self.problem(
                pos,
                f"type error: {what} differ: {_name(a)} and {_name(b)}",
                "both must have the same type",
            )
            return None
        return _known(a) or _known(b)

    def infer(self, e: ast.Expr) -> Ty:
        match e:
            case ast.Lit(value=v):
                return _lit_type(v)
            case ast.Var(name=n):
                d = self.decls.get(n)
                return None if d is None else _known(d.type)
            case ast.Index(expr=x):
                return self.infer(x)
            case ast.Unary(op="-", operand=x):
                return self.expect(x, _NUMERIC, "the operand of '-'")
            case ast.Unary(operand=x):
                self.expect(x, BOOL, "the operand of '!'")
                return BOOL
            case ast.Binary():
                return self.binary(e)
            case ast.If(cond=c, then=a, else_=b):
                self.expect(c, BOOL, "the condition of 'if'")
                return self.unify(self.infer(a), self.infer(b), b.pos, "the branches of 'if'")
            case ast.Call():
                return self.call(e)
            case ast.Eval(source=s, ascription=t):
                self.expect(s, STR, f"the source of {e.kind}(...)")
                return _known(t)
            case ast.ListLit(items=xs):
                elem: Ty = None
                for x in xs:
                    elem = self.unify(elem, self.infer(x), x.pos, "the items of a list")
                return ast.TList(elem or ast.TAny)
            case ast.MapLit(pairs=ps):
                val: Ty = None
                for _, x in ps:
                    val = self.unify(val, self.infer(x), x.pos, "the values of a map")
                return ast.TMap(val or ast.TAny)
            case ast.StructLit(fields=fs):
                keys = [k for k, _ in fs]
                if len(set(keys)) != len(keys):
                    dup = next(k for k in keys if keys.count(k) > 1)
                    self.problem(
                        e.pos, f"type error: field '{dup}' appears twice", "give each field once"
                    )
                return ast.TStruct(tuple((k, self.infer(x) or ast.TAny) for k, x in fs))
            case ast.TupleLit(items=xs):
                return ast.TTuple(tuple(self.infer(x) or ast.TAny for x in xs))
            case ast.Field():
                return self.field(e)
            case ast.Aggregate(expr=x, using=using):
                if using == "count":
                    self.infer(x)
                    return INT
                t = self.expect(x, _NUMERIC, f"the stream of aggregate(using: {using})")
                return FLOAT if using == "avg" else t

    def binary(self, e: ast.Binary) -> Ty:
        op = e.op
        if op in ("+", "-", "*", "/", "%"):
            hint = "concatenate strings with '++'" if op == "+" else ""
            ts = []
            for side, x in (("left", e.left), ("right", e.right)):
                t = self.infer(x)
                if t is not None and t not in _NUMERIC:
                    self.mismatch(x.pos, f"the {side} operand of '{op}'", "Int or Float", t, hint)
                    t = None
                ts.append(t)
            if FLOAT in ts:
                return FLOAT
            return INT if ts == [INT, INT] else None
        if op == "++":
            self.expect(e.left, STR, "the left operand of '++'")
            self.expect(e.right, STR, "the right operand of '++'")
            return STR
        if op in ("&&", "||", "=>"):
            self.expect(e.left, BOOL, f"the left operand of '{op}'")
            self.expect(e.right, BOOL, f"the right operand of '{op}'")
            return BOOL
        lt, rt = self.infer(e.left), self.infer(e.right)
        if op == "==":
            if not _compatible(lt, rt, numeric_mix=True):
                self.problem(
                    e.pos,
                    f"type error: '==' compares {_name(lt)} with {_name(rt)}",
                    "both sides must have the same type",
                )
            return BOOL
        ordered = (INT, FLOAT, STR)
        for side, t, x in (("left", lt, e.left), ("right", rt, e.right)):
            if t is not None and t not in ordered:
                self.mismatch(x.pos, f"the {side} operand of '{op}'", "Int, Float or Str", t)
                return BOOL
        if lt is not None and rt is not None and (lt == STR) != (rt == STR):
            self.problem(
                e.pos,
                f"type error: '{op}' compares {lt} with {rt}",
                "compare numbers with numbers and strings with strings",
            )
        return BOOL

    def call(self, e: ast.Call) -> Ty:
        if not self.call_shape_quiet(e):
            for a in e.args:
                self.infer(a)
            return None
        f, args = e.func, e.args
        if f in ("default", "init", "update"):
            what = f"the arguments of {f}(...)"
            return self.unify(self.infer(args[0]), self.infer(args[1]), args[1].pos, what)
        if f in ("is_defined", "when"):
            self.infer(args[0])
            return BOOL
        if f == "latch":
            self.infer(args[1])
            return self.infer(args[0])
        if f in ("sin", "cos", "tan"):
            self.expect(args[0], _NUMERIC, f"the argument of {f}")
            return FLOAT
        if f == "abs":
            return self.expect(args[0], _NUMERIC, "the argument of abs")
        if f == "timeout":
            self.infer(args[0])
            return BOOL
        if f.startswith("List."):
            return self.list_call(f, args)
        return self.map_call(f, args)

    def call_shape_quiet(self, e: ast.Call) -> bool:
        n = _ARITY.get(e.func)
        return n is not None and n == len(e.args)

    def container(self, x: ast.Expr, kind: type[ast.TList] | type[ast.TMap], what: str) -> Ty:
        """The element (value) type of list (map) ``x``: None if unknown or reported."""
        t = self.infer(x)
        if t is None:
            return None
        if isinstance(t, kind):
            return _known(t.elem if isinstance(t, ast.TList) else t.value)
        self.mismatch(x.pos, what, "a List" if kind is ast.TList else "a Map", t)
        return None

    def list_call(self, f: str, args: tuple[ast.Expr, ...]) -> Ty:
        elem = self.container(args[0], ast.TList, f"the first argument of {f}")
        if f == "List.get":
            self.expect(args[1], INT, "the index of List.get")
            return elem
        if f == "List.head":
            return elem
        if f == "List.tail":
            return ast.TList(elem or ast.TAny)
        if f == "List.len":
            return INT
        if f == "List.append":
            item = self.unify(elem, self.infer(args[1]), args[1].pos, "the list items and item")
            return ast.TList(item or ast.TAny)
        other = self.container(args[1], ast.TList, "the second argument of List.concat")
        both = self.unify(elem, other, args[1].pos, "the item types of List.concat")
        return ast.TList(both or ast.TAny)

    def map_call(self, f: str, args: tuple[ast.Expr, ...]) -> Ty:
        val = self.container(args[0], ast.TMap, f"the first argument of {f}")
        self.expect(args[1], STR, f"the key of {f}")
        if f == "Map.get":
            return val
        if f == "Map.has_key":
            return BOOL
        if f == "Map.insert":
            val = self.unify(val, self.infer(args[2]), args[2].pos, "the map values and value")
        return ast.TMap(val or ast.TAny)

    def field(self, e: ast.Field) -> Ty:
        t = self.infer(e.expr)
        if t is None:
            return None
        if isinstance(t, ast.TStruct):
            names = [k for k, _ in t.fields]
            for k, ft in t.fields:
                if k == e.name:
                    return _known(ft)
            close = difflib.get_close_matches(e.name, names, n=1)
            hint = f"did you mean '{close[0]}'? " if close else ""
            self.problem(
                e.pos, f"type error: {t} has no field '{e.name}'", hint + f"the fields: {names}"
            )
            return None
        if isinstance(t, ast.TTuple) and e.name.isdigit():
            i = int(e.name)
            if i < len(t.items):
                return _known(t.items[i])
            self.problem(
                e.pos,
                f"type error: {t} has no item {i}",
                f"tuple items count from 0 to {len(t.items) - 1}",
            )
            return None
        want = "a tuple" if e.name.isdigit() else "a struct"
        self.mismatch(e.pos, f"the value before '.{e.name}'", want, t)
        return None

    # -- cycles and memory -------------------------------------------------------------

    def cycles(self) -> None:
        for cycle, pos in _zero_cycles(self.spec):
            text = " -> ".join(cycle)
            self.problem(
                pos,
                f"zero-weight cycle {text}: every stream on it needs the others at the same tick",
                f"break it with an offset, e.g. {cycle[1]}[1] in the equation of {cycle[0]}",
            )

    def memory(self) -> None:
        need = memory_bound(self.spec, self.limits)
        if need <= self.limits.max_history_slots:
            return
        worst: _Ref | None = None
        for root in self.exprs():
            for r in _refs(root):
                if worst is None or r.weight > worst.weight:
                    worst = r
        pos = worst.index_pos if worst is not None and worst.weight else ast.Pos(1, 1)
        where = f"; the largest offset is {worst.name}[{worst.weight}]" if worst else ""
        self.problem(
            pos,
            f"the spec needs {need} history slots, more than the limit of "
            f"{self.limits.max_history_slots}{where}",
            "use smaller offsets, shorter aggregate windows, or raise Limits.max_history_slots",
        )


def _lit_type(v: object) -> Ty:
    t = type(v)
    if t is bool:
        return BOOL
    if t is int:
        return INT
    if t is float:
        return FLOAT
    if t is str:
        return STR
    if v is UNIT:
        return ast.TName("Unit")
    return None


def _zero_graph(spec: ast.Spec) -> tuple[list[str], dict[str, list[tuple[str, ast.Pos]]]]:
    """The computed streams in console order, and their weight-0 dependencies."""
    computed = {d.name for d in spec.decls if d.kind != "in"}
    names = [n for n in spec.order if n in computed]
    names += sorted(computed - set(names))
    deps: dict[str, list[tuple[str, ast.Pos]]] = {n: [] for n in names}
    done: set[str] = set()
    for eq in spec.equations:
        if eq.name not in computed or eq.name in done:
            continue
        done.add(eq.name)
        for r in _refs(eq.expr):
            if r.weight == 0 and r.name in computed and r.name not in (d for d, _ in deps[eq.name]):
                deps[eq.name].append((r.name, r.pos))
    return names, deps


def _zero_cycles(spec: ast.Spec) -> list[tuple[list[str], ast.Pos]]:
    """One cycle per strongly connected group of weight-0 dependencies, with the position
    of its first edge's reference."""
    names, deps = _zero_graph(spec)
    rank = {n: i for i, n in enumerate(names)}
    reported: set[str] = set()
    out: list[tuple[list[str], ast.Pos]] = []
    for start in names:
        if start in reported:
            continue
        # breadth-first search for the shortest way back to start
        prev: dict[str, str] = {}
        frontier = [start]
        found = False
        while frontier and not found:
            nxt: list[str] = []
            for n in frontier:
                for d, _ in sorted(deps[n], key=lambda dp: rank[dp[0]]):
                    if d == start:
                        prev[start] = n
                        found = True
                        break
                    if d not in prev and d != start:
                        prev[d] = n
                        nxt.append(d)
                if found:
                    break
            frontier = nxt
        if not found:
            continue
        chain = [prev[start]]
        while chain[-1] != start:
            chain.append(prev[chain[-1]])
        chain.reverse()  # start ... last, and last reads start
        cycle = [*chain, start]
        reported.update(cycle)
        first = next(p for d, p in deps[cycle[0]] if d == cycle[1])
        out.append((cycle, first))
    return out


def memory_bound(spec: ast.Spec, limits: Limits = Limits()) -> int:
    """History slots the spec needs: per stream the largest offset it is read at, plus
    ``dynamic_history`` per stream when the spec uses ``eval``/``defer``, plus
    ``window_samples`` per aggregate."""
    exprs = [eq.expr for eq in spec.equations] + [t.cond for t in spec.triggers]
    largest: dict[str, int] = {}
    dynamic = False
    aggregates = 0
    for root in exprs:
        for r in _refs(root):
            largest[r.name] = max(largest.get(r.name, 0), r.weight)
        for e in _walk(root):
            dynamic = dynamic or isinstance(e, ast.Eval)
            aggregates += isinstance(e, ast.Aggregate)
    streams = {d.name for d in spec.decls}
    total = sum(largest.values()) + aggregates * limits.window_samples
    if dynamic:
        total += limits.dynamic_history * len(streams)
    return total


def check_spec(spec: ast.Spec, limits: Limits = Limits()) -> list[Problem]:
    """Every static problem of ``spec`` (empty: it may run), sorted by position."""
    c = _Checker(spec, limits)
    c.equations()
    c.names_and_calls()
    c.types()
    c.cycles()
    c.memory()
    return sorted(c.problems, key=lambda p: (p.line, p.col))


def dependency_order(spec: ast.Spec) -> list[str]:
    """The out/aux streams, each after every stream its equation reads at offset 0 (ties
    in console order). Raises :class:`SpecError` on a zero-weight cycle."""
    names, deps = _zero_graph(spec)
    rank = {n: i for i, n in enumerate(names)}
    order: list[str] = []
    placed: set[str] = set()
    waiting = list(names)
    while waiting:
        ready = [n for n in waiting if all(d in placed for d, _ in deps[n])]
        if not ready:
            c = _Checker(spec, Limits())
            c.cycles()
            raise SpecError(c.problems)
        first = min(ready, key=rank.__getitem__)
        order.append(first)
        placed.add(first)
        waiting.remove(first)
    return order
