"""The parser: spec text (both syntax eras, RAP's extensions) to :mod:`.ast` nodes.

Recursive descent for statements, literals and postfix forms; precedence climbing for
the binary operators. Loosest to tightest::

    if c then a else b  <  ++  <  =>  <  ||  <  &&  <  == !=  <  < <= > >=
      <  + -  <  * / %  <  unary - !  <  postfix: f(a)  s.f  t.0  x[k]  x[-k, d]

``=>`` is right-associative, every other binary operator left-associative. ``if`` is
parsed where an operand is expected and takes everything to its right (like a lambda).

Positions: a node's ``pos`` is its operator for :class:`Binary`, :class:`Unary` and
:class:`Index` (the ``[``), the field name for :class:`Field` and ``aggregate`` for
:class:`Aggregate`, and its first token otherwise.

Syntax errors are collected: after one, the parser skips to the next line that starts a
statement (``in``/``out``/``aux``/``var``/``trigger`` or ``NAME =``), so a spec with
several broken lines reports them all in one :class:`SpecError`.
"""

from __future__ import annotations

import difflib
from fractions import Fraction
from typing import Final, Literal, NoReturn, cast

from trust_checker.errors import Problem, SpecError
from trust_checker.lang import ast
from trust_checker.lang.check import children
from trust_checker.lang.lexer import DURATION_UNITS, Lexeme, source_line, tokenize
from trust_checker.values import INT_MAX, INT_MIN, UNIT

__all__ = ["BINARY", "MAX_DEPTH", "MAX_NESTING", "parse_expr", "parse_spec"]

BINARY: Final[dict[str, tuple[int, bool]]] = {
    "++": (1, False),
    "=>": (2, True),
    "||": (3, False),
    "&&": (4, False),
    "==": (5, False),
    "!=": (5, False),
    "<": (6, False),
    "<=": (6, False),
    ">": (6, False),
    ">=": (6, False),
    "+": (7, False),
    "-": (7, False),
    "*": (8, False),
    "/": (8, False),
    "%": (8, False),
}
"""Binary operators: (binding power, right-associative?), loosest first."""

_SIMPLE_TYPES: Final = ("Int", "Float", "Str", "Bool", "Unit", "Any")
_ALL_TYPES: Final = (*_SIMPLE_TYPES, "List", "Map", "Struct")
_TYPE_ALIASES: Final = {
    "Integer": "Int",
    "int": "Int",
    "i64": "Int",
    "Long": "Int",
    "String": "Str",
    "string": "Str",
    "str": "Str",
    "Boolean": "Bool",
    "bool": "Bool",
    "Double": "Float",
    "float": "Float",
    "f64": "Float",
    "Real": "Float",
    "Number": "Float",
}
_TYPE_HINT: Final = (
    "the types are Int, Float, Str, Bool, Unit, Any, List<T>, Map<T>, "
    "Struct<a: T, ...> and tuples (T1, T2)"
)
_DECL_KINDS: Final = ("in", "out", "aux", "var")
_SEVERITIES: Final = ("info", "warning", "error", "critical")
_EVALS: Final = ("eval", "dynamic", "defer")
_DURATION_HINT: Final = "durations use ns, us, ms, s, min or h, e.g. 500ms, 2.5s, 1min"


MAX_NESTING: Final = 100
"""Most parentheses, brackets, calls and unary operators nested in one expression."""
MAX_DEPTH: Final = 250
"""Deepest syntax tree of one expression (a chain ``a + b + ...`` is as deep as long)."""


def _depth(root: ast.Expr) -> int:
    deepest = 0
    stack = [(root, 1)]
    while stack:
        e, d = stack.pop()
        deepest = max(deepest, d)
        stack.extend((c, d + 1) for c in children(e))
    return deepest


class _Fail(Exception):
    """One syntax error, already recorded; unwinds to the statement loop."""


def _describe(tok: Lexeme) -> str:
    return "the end of the text" if tok.kind == "EOF" else f"'{tok.text}'"


class _Parser:
    def __init__(self, text: str, path: str) -> None:
        self.text = text
        self.path = path
        self.tokens, self.problems = tokenize(text, path)
        self.lex_lines = {p.line for p in self.problems}
        self.i = 0
        self.order: list[str] = []
        self.seen: set[str] = set()
        self.nesting = 0

    # -- token helpers -------------------------------------------------------------------

    def peek(self, k: int = 0) -> Lexeme:
        return self.tokens[min(self.i + k, len(self.tokens) - 1)]

    def next(self) -> Lexeme:
        tok = self.tokens[self.i]
        if tok.kind != "EOF":
            self.i += 1
        return tok

    def accept(self, kind: str) -> Lexeme | None:
        if self.peek().kind == kind:
            return self.next()
        return None

    def fail(self, tok: Lexeme, message: str, hint: str = "") -> NoReturn:
        if tok.kind == "EOF" and self.i > 0:  # point just after the last token
            last = self.tokens[self.i - 1]
            tail = last.text.splitlines()[-1] if last.text else ""
            col = last.col + len(tail) if "\n" not in last.text else len(tail) + 1
            tok = Lexeme("EOF", "", last.line + last.text.count("\n"), col, False)
        if tok.line not in self.lex_lines:  # a lexical error there says it already
            self.problems.append(
                Problem(
                    self.path, tok.line, tok.col, message, source_line(self.text, tok.line), hint
                )
            )
        raise _Fail

    def expect(self, kind: str, what: str, hint: str = "") -> Lexeme:
        tok = self.peek()
        if tok.kind != kind:
            self.fail(tok, f"expected {what}, found {_describe(tok)}", hint)
        return self.next()

    @staticmethod
    def pos(tok: Lexeme) -> ast.Pos:
        return ast.Pos(tok.line, tok.col)

    def see(self, name: str) -> None:
        if name not in self.seen:
            self.seen.add(name)
            self.order.append(name)

    def between(self, first: Lexeme, last: Lexeme) -> str:
        return self.text[first.start : last.end]

    # -- statements ----------------------------------------------------------------------

    def starts_statement(self, j: int) -> bool:
        tok = self.tokens[j]
        if tok.kind in _DECL_KINDS or tok.kind == "trigger":
            return True
        return tok.kind == "NAME" and self.tokens[min(j + 1, len(self.tokens) - 1)].kind == "="

    def recover(self, start: int) -> None:
        """Skip to the next line that starts a statement after the one at ``start``."""
        self.i = start
        self.next()
        while self.peek().kind != "EOF" and not (self.peek().bol and self.starts_statement(self.i)):
            self.next()

    def spec(self) -> ast.Spec:
        decls: list[ast.Decl] = []
        equations: list[ast.Equation] = []
        triggers: list[ast.Trigger] = []
        while self.peek().kind != "EOF":
            start = self.i
            try:
                tok = self.peek()
                if tok.kind in _DECL_KINDS:
                    decls.append(self.decl())
                elif tok.kind == "trigger":
                    triggers.append(self.trigger())
                elif tok.kind == "NAME" and self.peek(1).kind == "=":
                    equations.append(self.equation())
                else:
                    hint = "a spec is made of declarations (in x: Int), equations (y = x + 1)"
                    hint += ' and triggers (trigger y > 3 "too high")'
                    if tok.kind == "NAME" and self.peek(1).kind == ":":
                        hint = f"declare it first: in {tok.text}: T (or out/aux)"
                    self.fail(
                        tok, f"expected a declaration or an equation, found {_describe(tok)}", hint
                    )
                end = self.peek()
                if end.kind != "EOF" and not self.starts_statement(self.i):
                    hint = "one declaration or equation per line; is an operator missing?"
                    if end.kind == "=":
                        hint = "compare with '=='"
                    self.fail(
                        end, f"unexpected {_describe(end)} after the end of the statement", hint
                    )
            except _Fail:
                self.recover(start)
        if self.problems:
            raise SpecError(sorted(self.problems, key=lambda p: (p.line, p.col)))
        return ast.Spec(
            tuple(decls),
            tuple(equations),
            tuple(triggers),
            tuple(self.order),
            source=self.text,
            path=self.path,
        )

    def decl(self) -> ast.Decl:
        kw = self.next()
        kind = cast(Literal["in", "out", "aux"], "aux" if kw.kind == "var" else kw.kind)
        tok = self.peek()
        if tok.kind != "NAME":
            hint = f"a declaration names its stream: {kw.text} NAME: T"
            if tok.kind in _DECL_KINDS or tok.kind in ("if", "then", "else", "true", "false"):
                hint = f"'{tok.text}' is a keyword; choose another stream name"
            self.fail(
                tok, f"expected a stream name after '{kw.text}', found {_describe(tok)}", hint
            )
        self.next()
        self.see(tok.text)
        typ: ast.Type | None = None
        if self.accept(":"):
            typ = self.type_()
        period: int | None = None
        at = self.accept("@")
        if at is not None:
            if kind == "in":
                self.fail(
                    at,
                    f"input '{tok.text}' cannot have a rate",
                    "inputs tick when a value arrives; rates are for outputs: out y @ 10Hz",
                )
            period = self.rate()
        return ast.Decl(kind, tok.text, typ, period, self.pos(kw))

    def equation(self) -> ast.Equation:
        name = self.next()
        self.see(name.text)
        self.next()  # "="
        return ast.Equation(name.text, self.top_expr(), self.pos(name))

    def trigger(self) -> ast.Trigger:
        kw = self.next()
        cond = self.top_expr()
        msg = self.expect(
            "STR",
            "the trigger's message",
            'write trigger COND "message" [info|warning|error|critical]',
        )
        severity = "warning"
        tok = self.peek()
        if tok.kind == "NAME" and tok.line == msg.line and self.peek(1).kind != "=":
            if tok.text not in _SEVERITIES:
                close = difflib.get_close_matches(tok.text, _SEVERITIES, n=1)
                self.fail(
                    tok,
                    f"unknown severity '{tok.text}'",
                    (f"did you mean {close[0]}? " if close else "")
                    + "the severities are info, warning, error and critical",
                )
            severity = self.next().text
        sev = cast(Literal["info", "warning", "error", "critical"], severity)
        return ast.Trigger(cond, cast(str, msg.value), sev, self.pos(kw))

    # -- types, durations, rates ---------------------------------------------------------

    def type_(self) -> ast.Type:
        tok = self.next()
        if tok.kind == "(":
            if self.accept(")"):
                return ast.TName("Unit")
            items = [self.type_()]
            while self.accept(","):
                items.append(self.type_())
            self.expect(")", "',' or ')' in a tuple type", "a tuple type is (T1, T2)")
            return items[0] if len(items) == 1 else ast.TTuple(tuple(items))
        if tok.kind != "NAME":
            self.fail(tok, f"expected a type, found {_describe(tok)}", _TYPE_HINT)
        name = tok.text
        if name in _SIMPLE_TYPES:
            return ast.TName(cast(Literal["Int", "Float", "Str", "Bool", "Unit", "Any"], name))
        if name == "List":
            self.expect("<", "'<' after List", "write List<T>, e.g. List<Int>")
            elem = self.type_()
            self.expect(">", "'>' to close List<...>", "write List<T>, e.g. List<Int>")
            return ast.TList(elem)
        if name == "Map":
            self.expect("<", "'<' after Map", "write Map<T> (keys are strings), e.g. Map<Int>")
            first_tok = self.peek()
            value = self.type_()
            if self.accept(","):
                if value != ast.TName("Str"):
                    self.fail(first_tok, f"map keys must be Str, found {value}", "write Map<T>")
                value = self.type_()
            self.expect(">", "'>' to close Map<...>", "write Map<T>, e.g. Map<Int>")
            return ast.TMap(value)
        if name == "Struct":
            self.expect("<", "'<' after Struct", "write Struct<a: T, b: T>")
            fields: list[tuple[str, ast.Type]] = []
            while True:
                fname = self.expect("NAME", "a field name", "write Struct<a: T, b: T>")
                self.expect(":", f"':' after the field name '{fname.text}'", "write Struct<a: T>")
                fields.append((fname.text, self.type_()))
                if not self.accept(","):
                    break
            self.expect(">", "',' or '>' in Struct<...>", "write Struct<a: T, b: T>")
            return ast.TStruct(tuple(fields))
        guess = _TYPE_ALIASES.get(name) or next(
            iter(difflib.get_close_matches(name, _ALL_TYPES, n=1)), None
        )
        hint = f"did you mean {guess}? " if guess else ""
        self.fail(tok, f"unknown type '{name}'", hint + _TYPE_HINT)

    def duration(self, what: str) -> int:
        """A duration token in nanoseconds (``500ms``, ``2.5s``, ``1min``)."""
        tok = self.next()
        if tok.kind in ("INT", "FLOAT"):
            self.fail(tok, f"{what} '{tok.text}' has no unit", f"write {tok.text}s or {tok.text}ms")
        if tok.kind != "QTY":
            self.fail(tok, f"expected {what} (a duration), found {_describe(tok)}", _DURATION_HINT)
        number, unit = cast(tuple[str, str], tok.value)
        if unit not in DURATION_UNITS:
            self.fail(tok, f"unknown time unit '{unit}' in '{tok.text}'", _DURATION_HINT)
        ns = round(Fraction(number) * DURATION_UNITS[unit])
        if ns <= 0:
            self.fail(tok, f"{what} '{tok.text}' must be longer than zero", _DURATION_HINT)
        return ns

    def rate(self) -> int:
        """After ``@``: ``10Hz`` (or a period like ``100ms``), as a period in ns."""
        tok = self.peek()
        if tok.kind in ("INT", "FLOAT") and self.peek(1).kind == "NAME":
            unit_tok = self.peek(1)
            if unit_tok.text == "Hz":  # "10 Hz"
                self.next()
                self.next()
                return self.period_of(tok, tok.text)
        if tok.kind == "QTY":
            number, unit = cast(tuple[str, str], tok.value)
            if unit == "Hz":
                self.next()
                return self.period_of(tok, number)
            if unit in DURATION_UNITS:
                return self.duration("the period")
        self.fail(
            tok,
            f"expected a rate after '@', found {_describe(tok)}",
            "write a rate in Hz (out y @ 10Hz) or a period (out y @ 100ms)",
        )

    def period_of(self, tok: Lexeme, number: str) -> int:
        hz = Fraction(number)
        if hz <= 0:
            self.fail(tok, f"rate '{tok.text}' must be more than zero", "e.g. out y @ 10Hz")
        return round(Fraction(1_000_000_000) / hz)

    # -- expressions ---------------------------------------------------------------------

    def top_expr(self) -> ast.Expr:
        """A whole expression, no deeper than :data:`MAX_DEPTH` (the checker and the
        evaluator walk trees recursively)."""
        first = self.peek()
        e = self.expr()
        depth = _depth(e)
        if depth > MAX_DEPTH:
            self.fail(
                first,
                f"expression is {depth} levels deep, more than {MAX_DEPTH}",
                "split it into aux streams (aux part = ...)",
            )
        return e

    def expr(self) -> ast.Expr:
        return self.binary(1)

    def binary(self, min_bp: int) -> ast.Expr:
        self.nesting += 1
        try:
            if self.nesting > MAX_NESTING:
                self.fail(
                    self.peek(),
                    f"expression nested more than {MAX_NESTING} levels deep",
                    "split it into aux streams (aux part = ...)",
                )
            return self.binary_rest(min_bp)
        finally:
            self.nesting -= 1

    def binary_rest(self, min_bp: int) -> ast.Expr:
        left = self.unary()
        while True:
            tok = self.peek()
            info = BINARY.get(tok.kind)
            if info is None or info[0] < min_bp:
                return left
            bp, right_assoc = info
            self.next()
            right = self.binary(bp if right_assoc else bp + 1)
            pos = self.pos(tok)
            if tok.kind == "!=":
                left = ast.Unary("!", ast.Binary("==", left, right, pos), pos)
            else:
                left = ast.Binary(cast(ast.BinOp, tok.kind), left, right, pos)

    def unary(self) -> ast.Expr:
        tok = self.peek()
        if tok.kind not in ("-", "!"):
            return self.postfix(self.primary())
        self.next()
        lit = self.peek()
        if tok.kind == "-" and lit.kind in ("INT", "FLOAT"):
            self.next()
            value = -cast(float, lit.value)
            if lit.kind == "INT" and value < INT_MIN:
                self.int_range(lit, f"-{lit.text}")
            return self.postfix(ast.Lit(value, self.pos(tok)))
        self.nesting += 1
        try:
            if self.nesting > MAX_NESTING:
                self.fail(tok, f"more than {MAX_NESTING} unary operators in a row", "remove some")
            operand = self.unary()
        finally:
            self.nesting -= 1
        return ast.Unary(cast(Literal["-", "!"], tok.kind), operand, self.pos(tok))

    def int_range(self, tok: Lexeme, text: str) -> NoReturn:
        self.fail(
            tok,
            f"integer literal {text} does not fit in 64 bits",
            f"Int is 64-bit, from {INT_MIN} to {INT_MAX}; write a Float with a dot",
        )

    def primary(self) -> ast.Expr:
        tok = self.next()
        pos = self.pos(tok)
        kind = tok.kind
        if kind == "INT":
            if cast(int, tok.value) > INT_MAX:
                self.int_range(tok, tok.text)
            return ast.Lit(tok.value, pos)
        if kind in ("FLOAT", "STR"):
            return ast.Lit(tok.value, pos)
        if kind in ("true", "false"):
            return ast.Lit(kind == "true", pos)
        if kind == "if":
            return self.if_(tok)
        if kind == "(":
            return self.paren(tok)
        if kind == "[":
            items = self.items("]", "a list")
            return ast.ListLit(tuple(items), pos)
        if kind == "{":
            return ast.StructLit(tuple(self.pairs("}", "a struct", strings_only=False)), pos)
        if kind == "NAME":
            return self.name(tok)
        if kind == "QTY":
            unit = cast(tuple[str, str], tok.value)[1]
            if unit in DURATION_UNITS or unit == "Hz":
                self.fail(
                    tok,
                    f"a {'rate' if unit == 'Hz' else 'duration'} '{tok.text}' cannot be a value",
                    "durations go in timeout(x, 2s) and x.aggregate(over: 5s, using: avg); "
                    "rates in out y @ 10Hz",
                )
            self.fail(tok, f"unexpected '{tok.text}'", "a name cannot start with a digit")
        hint = "an operand is a literal, a stream name, a call, a list [..] or (..)"
        if kind == "=":
            hint = "compare with '=='"
        elif kind in ("then", "else"):
            hint = f"'{kind}' belongs to if c then a else b"
        self.fail(tok, f"expected an expression, found {_describe(tok)}", hint)

    def if_(self, tok: Lexeme) -> ast.Expr:
        cond = self.expr()
        self.expect("then", "'then' after the condition of 'if'", "write if c then a else b")
        then = self.expr()
        self.expect(
            "else",
            "'else' after the 'then' branch of 'if'",
            "every if needs both branches: if c then a else b",
        )
        return ast.If(cond, then, self.expr(), self.pos(tok))

    def paren(self, tok: Lexeme) -> ast.Expr:
        if self.accept(")"):
            return ast.Lit(UNIT, self.pos(tok))
        first = self.expr()
        if self.accept(")"):
            return first
        items = [first]
        while self.accept(","):
            items.append(self.expr())
        self.expect(")", "',' or ')'", f"close the '(' opened at {tok.line}:{tok.col}")
        return ast.TupleLit(tuple(items), self.pos(tok))

    def items(self, close: str, what: str) -> list[ast.Expr]:
        """Comma-separated expressions up to ``close`` (consumed)."""
        out: list[ast.Expr] = []
        if self.accept(close):
            return out
        while True:
            out.append(self.expr())
            if self.accept(close):
                return out
            self.expect(
                ",", f"',' or '{close}' in {what}", f"separate the items of {what} with ','"
            )

    def pairs(self, close: str, what: str, *, strings_only: bool) -> list[tuple[str, ast.Expr]]:
        """``key: expr`` pairs up to ``close``; keys are strings (and names, for structs)."""
        out: list[tuple[str, ast.Expr]] = []
        if self.accept(close):
            return out
        example = 'Map("k": 1)' if strings_only else '{k: 1} or Struct("k": 1)'
        while True:
            key = self.next()
            if key.kind not in ("STR", "NAME") or (strings_only and key.kind == "NAME"):
                self.fail(
                    key, f"expected a key in {what}, found {_describe(key)}", f"write {example}"
                )
            self.expect(":", f"':' after the key {key.text}", f"write {example}")
            out.append((cast(str, key.value), self.expr()))
            if self.accept(close):
                return out
            self.expect(",", f"',' or '{close}' in {what}", f"write {example}")

    def name(self, tok: Lexeme) -> ast.Expr:
        name = tok.text
        if (
            name in ("List", "Map")
            and self.peek().kind == "."
            and self.peek(1).kind == "NAME"
            and self.peek(2).kind == "("
        ):
            self.next()
            name = f"{name}.{self.next().text}"
        if self.peek().kind != "(":
            self.see(name)
            return ast.Var(name, self.pos(tok))
        self.next()  # "("
        pos = self.pos(tok)
        if name in _EVALS:
            return self.eval_(tok)
        if name == "List":
            return ast.ListLit(tuple(self.items(")", "List(...)")), pos)
        if name == "Map":
            return ast.MapLit(tuple(self.pairs(")", "Map(...)", strings_only=True)), pos)
        if name == "Struct":
            return ast.StructLit(tuple(self.pairs(")", "Struct(...)", strings_only=False)), pos)
        if name == "timeout":
            arg = self.expr()
            self.expect(",", "',' and a duration in timeout(x, 2s)", "write timeout(x, 2s)")
            dur_tok = self.peek()
            ns = self.duration("the timeout")
            self.expect(")", "')' after timeout(x, duration", "write timeout(x, 2s)")
            return ast.Call("timeout", (arg, ast.Lit(ns, self.pos(dur_tok))), pos)
        return ast.Call(name, tuple(self.items(")", f"the arguments of {name}(...)")), pos)

    def eval_(self, tok: Lexeme) -> ast.Expr:
        source = self.expr()
        ascription: ast.Type | None = None
        scope: tuple[str, ...] | None = None
        if self.accept(":"):
            ascription = self.type_()
        if self.accept(","):
            self.expect("{", "'{' to open the scope", f"write {tok.text}(s: T, {{x, y}})")
            names: list[str] = []
            if not self.accept("}"):
                while True:
                    n = self.expect("NAME", "a stream name in the scope", "write {x, y}")
                    self.see(n.text)
                    names.append(n.text)
                    if self.accept("}"):
                        break
                    self.expect(",", "',' or '}' in the scope", "write {x, y}")
            scope = tuple(names)
        self.expect(
            ")",
            f"')' to close {tok.text}(...)",
            f"write {tok.text}(s), {tok.text}(s: T) or {tok.text}(s: T, {{x, y}})",
        )
        kind: Literal["eval", "defer"] = "defer" if tok.text == "defer" else "eval"
        return ast.Eval(source, kind, ascription, scope, self.pos(tok))

    def postfix(self, node: ast.Expr) -> ast.Expr:
        while True:
            tok = self.peek()
            if tok.kind == ".":
                self.next()
                node = self.member(node)
            elif tok.kind == "[":
                node = self.index(node)
            else:
                return node

    def member(self, node: ast.Expr) -> ast.Expr:
        tok = self.next()
        if tok.kind == "INT":
            return ast.Field(node, tok.text, self.pos(tok))
        if tok.kind != "NAME":
            self.fail(
                tok,
                f"expected a field name after '.', found {_describe(tok)}",
                "write s.field for a struct or t.0 for a tuple",
            )
        if self.peek().kind == "(":
            if tok.text == "aggregate":
                return self.aggregate(node, tok)
            self.fail(
                tok,
                f"'{tok.text}(...)' is not a method",
                "call built-ins as functions, e.g. List.len(l); the only method is "
                "x.aggregate(over: 5s, using: avg)",
            )
        return ast.Field(node, tok.text, self.pos(tok))

    def aggregate(self, node: ast.Expr, tok: Lexeme) -> ast.Expr:
        example = "write x.aggregate(over: 5s, using: count|sum|avg|min|max)"
        self.next()  # "("
        over: int | None = None
        using: str | None = None
        while True:
            key = self.expect("NAME", "'over:' or 'using:'", example)
            self.expect(":", f"':' after '{key.text}'", example)
            if key.text == "over":
                over = self.duration("the window")
            elif key.text == "using":
                fn = self.expect("NAME", "an aggregate function", example)
                if fn.text not in ast.AGGREGATES:
                    close = difflib.get_close_matches(fn.text, sorted(ast.AGGREGATES), n=1)
                    self.fail(
                        fn,
                        f"unknown aggregate '{fn.text}'",
                        (f"did you mean {close[0]}? " if close else "") + example,
                    )
                using = fn.text
            else:
                self.fail(key, f"unknown argument '{key.text}' of aggregate", example)
            if self.accept(")"):
                break
            self.expect(",", "',' or ')'", example)
        if over is None or using is None:
            missing = "over" if over is None else "using"
            self.fail(tok, f"aggregate needs '{missing}:'", example)
        agg = cast(Literal["count", "sum", "avg", "min", "max"], using)
        return ast.Aggregate(node, over, agg, self.pos(tok))

    def index(self, node: ast.Expr) -> ast.Expr:
        lb = self.next()
        neg = self.accept("-") is not None
        k = self.next()
        if k.kind != "INT":
            self.fail(
                k,
                f"a stream offset must be an integer literal, found {_describe(k)}",
                "write x[1] for the previous value, or x[-1, d] with a default (D5.2 form)",
            )
        offset = cast(int, k.value)
        default: ast.Expr | None = None
        first_default = self.peek(1)
        if self.accept(",") is not None:
            default = self.expr()
        last_default = self.tokens[self.i - 1]
        self.expect("]", "']' to close the offset", "write x[1] or x[-1, d]")
        if not neg and default is not None and offset > 0:
            base = node.name if isinstance(node, ast.Var) else "x"
            dtext = self.between(first_default, last_default)
            self.fail(
                k,
                f"future offset in '{base}[{offset}, {dtext}]': only past values can be read",
                f"past offsets are negative in this form: {base}[-{offset}, {dtext}]",
            )
        idx = ast.Index(node, offset, self.pos(lb))
        if default is None:
            return idx
        return ast.Call("default", (idx, default), self.pos(lb))


def parse_spec(text: str, path: str = "<spec>") -> ast.Spec:
    """Parse a whole spec; :class:`SpecError` lists every syntax error found."""
    return _Parser(text, path).spec()


def parse_expr(text: str, path: str = "<expr>") -> ast.Expr:
    """Parse one expression (an ``eval`` string, a trace file value)."""
    p = _Parser(text, path)
    try:
        if p.peek().kind == "EOF":
            p.fail(p.peek(), "expected an expression, found nothing", "e.g. x + 1")
        expr = p.top_expr()
        end = p.peek()
        if end.kind != "EOF":
            p.fail(
                end, f"unexpected {_describe(end)} after the expression", "is an operator missing?"
            )
    except _Fail:
        pass
    if p.problems:
        raise SpecError(sorted(p.problems, key=lambda q: (q.line, q.col)))
    return expr
