"""The parser: every form of the language, both eras, RAP's extensions, syntax errors."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from trust_checker.errors import Problem, SpecError
from trust_checker.lang import ast, check_spec
from trust_checker.lang.ast import (
    Aggregate,
    Binary,
    Call,
    Decl,
    Equation,
    Eval,
    Field,
    If,
    Index,
    ListLit,
    Lit,
    MapLit,
    Pos,
    StructLit,
    TList,
    TMap,
    TName,
    Trigger,
    TStruct,
    TTuple,
    TupleLit,
    Unary,
    Var,
)
from trust_checker.lang.parser import parse_expr, parse_spec
from trust_checker.values import INT_MAX, INT_MIN, UNIT

a, b, c, d, x = Var("a"), Var("b"), Var("c"), Var("d"), Var("x")
INT, FLOAT, STR, BOOL = TName("Int"), TName("Float"), TName("Str"), TName("Bool")


def B(op: ast.BinOp, left: ast.Expr, right: ast.Expr) -> Binary:
    return Binary(op, left, right)


def problems(text: str) -> list[Problem]:
    with pytest.raises(SpecError) as info:
        parse_spec(text, "t.lola")
    return info.value.problems


# -- declarations ----------------------------------------------------------------------


def test_every_declaration_form() -> None:
    spec = parse_spec("in a\nin b: Int\nout c: Bool\naux d\nvar e: Float\nout f\n")
    assert spec.decls == (
        Decl("in", "a"),
        Decl("in", "b", INT),
        Decl("out", "c", BOOL),
        Decl("aux", "d"),
        Decl("aux", "e", FLOAT),  # var is an alias of aux
        Decl("out", "f"),
    )
    assert spec.inputs == ("a", "b")
    assert spec.decls[4].pos == Pos(5, 1)


def test_equations_and_order_of_first_appearance() -> None:
    spec = parse_spec("out z\nz = y + w\nin w\nin y\nout q\nq = z", "spec.dsrv")
    assert spec.equations == (Equation("z", B("+", Var("y"), Var("w"))), Equation("q", Var("z")))
    assert spec.order == ("z", "y", "w", "q")
    assert spec.outputs == ("z", "q")
    assert spec.path == "spec.dsrv"
    assert spec.source.startswith("out z\n")
    assert spec.equations[1].pos == Pos(6, 1)


def test_order_counts_uses_in_triggers_and_eval_scopes() -> None:
    spec = parse_spec('out y\ntrigger k > 1 "m"\ny = eval(s, {u, v})')
    assert spec.order == ("y", "k", "s", "u", "v")


def test_declarations_and_equations_in_any_order_with_multiline_expressions() -> None:
    spec = parse_spec("y = x +\n    1\n\nout y\nin x")
    assert spec.equations == (Equation("y", B("+", x, Lit(1))),)
    assert [dl.name for dl in spec.decls] == ["y", "x"]


def test_comments() -> None:
    spec = parse_spec(
        "// header\nin x: Int // trailing\n(* a block\n   over lines *) out y\n"
        'y = x (* inside *) + 1 // end\nout s\ns = "(* not a comment // either *)"\n'
    )
    assert [dl.name for dl in spec.decls] == ["x", "y", "s"]
    assert spec.equations[0].expr == B("+", x, Lit(1))
    assert spec.equations[1].expr == Lit("(* not a comment // either *)")


# -- types -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("Int", INT),
        ("Float", FLOAT),
        ("Str", STR),
        ("Bool", BOOL),
        ("Unit", TName("Unit")),
        ("Any", ast.TAny),
        ("List<Int>", TList(INT)),
        ("List<List<Str>>", TList(TList(STR))),
        ("Map<Float>", TMap(FLOAT)),
        ("Map<Str, Bool>", TMap(BOOL)),
        ("Struct<a: Int, b: List<Str>>", TStruct((("a", INT), ("b", TList(STR))))),
        ("(Int, Bool)", TTuple((INT, BOOL))),
        ("(Int, (Str, Float))", TTuple((INT, TTuple((STR, FLOAT))))),
        ("()", TName("Unit")),
        ("(Int)", INT),
    ],
)
def test_types(text: str, expected: ast.Type) -> None:
    assert parse_spec(f"in x: {text}").decls[0].type == expected


# -- literals --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("42", Lit(42)),
        ("-7", Lit(-7)),
        ("0", Lit(0)),
        (str(INT_MAX), Lit(INT_MAX)),
        (str(INT_MIN), Lit(INT_MIN)),
        ("1.5", Lit(1.5)),
        ("-2.25", Lit(-2.25)),
        ("true", Lit(True)),
        ("false", Lit(False)),
        ('"plain"', Lit("plain")),
        (r'"a\nb\tc\"d\\e"', Lit('a\nb\tc"d\\e')),
        ('""', Lit("")),
        ("()", Lit(UNIT)),
        ("[1, 2]", ListLit((Lit(1), Lit(2)))),
        ("[]", ListLit(())),
        ("List(1, x)", ListLit((Lit(1), x))),
        ("List()", ListLit(())),
        ('Map("k": 1, "j": x)', MapLit((("k", Lit(1)), ("j", x)))),
        ("Map()", MapLit(())),
        ('Struct("k": 1)', StructLit((("k", Lit(1)),))),
        ("{k: 1, j: true}", StructLit((("k", Lit(1)), ("j", Lit(True))))),
        ('{"k": 1}', StructLit((("k", Lit(1)),))),
        ("(1, x)", TupleLit((Lit(1), x))),
        ("(1, 2, 3)", TupleLit((Lit(1), Lit(2), Lit(3)))),
        ("(1)", Lit(1)),
    ],
)
def test_literals(text: str, expected: ast.Expr) -> None:
    assert parse_expr(text) == expected


def test_literal_value_types_are_exact() -> None:
    assert type(parse_expr("3").value) is int  # type: ignore[union-attr]
    assert type(parse_expr("3.0").value) is float  # type: ignore[union-attr]
    assert parse_expr("()").value is UNIT  # type: ignore[union-attr]
    assert type(parse_expr("true").value) is bool  # type: ignore[union-attr]


# -- operators -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("a + b * c", B("+", a, B("*", b, c))),
        ("a * b + c", B("+", B("*", a, b), c)),
        ("a - b - c", B("-", B("-", a, b), c)),
        ("a / b % c", B("%", B("/", a, b), c)),
        ("a * b / c", B("/", B("*", a, b), c)),
        ("a + b < c - d", B("<", B("+", a, b), B("-", c, d))),
        ("a <= b == c >= d", B("==", B("<=", a, b), B(">=", c, d))),
        ("a > b", B(">", a, b)),
        ("a == b == c", B("==", B("==", a, b), c)),
        ("a == b && c", B("&&", B("==", a, b), c)),
        ("a && b || c && d", B("||", B("&&", a, b), B("&&", c, d))),
        ("a || b && c", B("||", a, B("&&", b, c))),
        ("a || b => c", B("=>", B("||", a, b), c)),
        ("a => b => c", B("=>", a, B("=>", b, c))),
        ("a => b ++ c", B("++", B("=>", a, b), c)),
        ("a ++ b ++ c", B("++", B("++", a, b), c)),
        ("a != b", Unary("!", B("==", a, b))),
        ("a != b && c", B("&&", Unary("!", B("==", a, b)), c)),
        ("!a && b", B("&&", Unary("!", a), b)),
        ("-a * b", B("*", Unary("-", a), b)),
        ("- -a", Unary("-", Unary("-", a))),
        ("!!a", Unary("!", Unary("!", a))),
        ("a - -1", B("-", a, Lit(-1))),
        ("-(1)", Unary("-", Lit(1))),
        ("-x[1]", Unary("-", Index(x, 1))),
        ("!s.f", Unary("!", Field(Var("s"), "f"))),
        ("(a + b) * c", B("*", B("+", a, b), c)),
        ("if a then b else c", If(a, b, c)),
        ("if a then b else c ++ d", If(a, b, B("++", c, d))),
        ("if a ++ b then c else d", If(B("++", a, b), c, d)),
        ("1 + if a then b else c", B("+", Lit(1), If(a, b, c))),
        ("if a then if b then c else d else x", If(a, If(b, c, d), x)),
        ("(if a then b else c) + 1", B("+", If(a, b, c), Lit(1))),
    ],
)
def test_precedence_and_associativity(text: str, expected: ast.Expr) -> None:
    assert parse_expr(text) == expected


def test_positions_point_at_operators_and_first_tokens() -> None:
    e = parse_expr("a +\n  b * c")
    assert isinstance(e, Binary)
    assert e.pos == Pos(1, 3)
    assert e.right.pos == Pos(2, 5)
    assert e.left.pos == Pos(1, 1)
    call = parse_expr("  default(x, 1)")
    assert call.pos == Pos(1, 3)


# -- postfix forms and built-ins ------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("s.f", Field(Var("s"), "f")),
        ("s.f.g", Field(Field(Var("s"), "f"), "g")),
        ("t.0", Field(Var("t"), "0")),
        ("t.0.1", Field(Field(Var("t"), "0"), "1")),
        ("x[1]", Index(x, 1)),
        ("x[0]", Index(x, 0)),
        ("x[1][2]", Index(Index(x, 1), 2)),
        ("(a + b)[3]", Index(B("+", a, b), 3)),
        ("x[-1]", Index(x, 1)),
        ("x[-2, 0]", Call("default", (Index(x, 2), Lit(0)))),
        ("x[-1, a + 1]", Call("default", (Index(x, 1), B("+", a, Lit(1))))),
        ("x[0, 5]", Call("default", (Index(x, 0), Lit(5)))),
        ("default(x[1], 0)", Call("default", (Index(x, 1), Lit(0)))),
        ("init(x, 0)", Call("init", (x, Lit(0)))),
        ("is_defined(x)", Call("is_defined", (x,))),
        ("when(x)", Call("when", (x,))),
        ("latch(x, a)", Call("latch", (x, a))),
        ("update(a, b)", Call("update", (a, b))),
        ("sin(x) + abs(x)", B("+", Call("sin", (x,)), Call("abs", (x,)))),
        ("List.get(l, 0)", Call("List.get", (Var("l"), Lit(0)))),
        ("List.len(l)", Call("List.len", (Var("l"),))),
        ('Map.insert(m, "k", 1)', Call("Map.insert", (Var("m"), Lit("k"), Lit(1)))),
        ('Map.has_key(m, "k")', Call("Map.has_key", (Var("m"), Lit("k")))),
        ("List.get(l, 0).f", Field(Call("List.get", (Var("l"), Lit(0))), "f")),
        ("frob(1)", Call("frob", (Lit(1),))),  # unknown functions are check.py's
    ],
)
def test_postfix_and_calls(text: str, expected: ast.Expr) -> None:
    assert parse_expr(text) == expected


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("eval(s)", Eval(Var("s"), "eval")),
        ("dynamic(s)", Eval(Var("s"), "eval")),
        ("defer(s)", Eval(Var("s"), "defer")),
        ("eval(s: Int)", Eval(Var("s"), "eval", INT)),
        ("eval(s, {x, y})", Eval(Var("s"), "eval", None, ("x", "y"))),
        ("eval(s, {})", Eval(Var("s"), "eval", None, ())),
        ("dynamic(s: List<Int>, {x})", Eval(Var("s"), "eval", TList(INT), ("x",))),
        ('defer("x + 1")', Eval(Lit("x + 1"), "defer")),
    ],
)
def test_eval_forms(text: str, expected: ast.Expr) -> None:
    assert parse_expr(text) == expected


def test_both_eras_give_the_same_tree() -> None:
    d52 = parse_spec("in x: Int\nout y: Int\ny = x[-1, 0] + x[-2]\n")
    now = parse_spec("in x: Int\nout y: Int\ny = default(x[1], 0) + x[2]\n")
    assert d52 == now


# -- RAP extensions --------------------------------------------------------------------


@pytest.mark.parametrize(
    ("decl", "period"),
    [
        ("out y @ 10Hz", 100_000_000),
        ("out y: Int @ 2.5Hz", 400_000_000),
        ("out y @ 10 Hz", 100_000_000),
        ("out y @ 100ms", 100_000_000),
        ("aux y: Bool @ 1Hz", 1_000_000_000),
        ("out y", None),
    ],
)
def test_periodic_outputs(decl: str, period: int | None) -> None:
    assert parse_spec(decl).decls[0].period_ns == period


def test_triggers() -> None:
    spec = parse_spec(
        'in x: Int\ntrigger x > 3 "too high"\ntrigger x < 0 "negative" critical\n'
        'trigger x == 1 "one"\nerror = x\ntrigger true "i" info\n'
    )
    assert spec.triggers == (
        Trigger(B(">", x, Lit(3)), "too high"),
        Trigger(B("<", x, Lit(0)), "negative", "critical"),
        Trigger(B("==", x, Lit(1)), "one", "warning"),
        Trigger(Lit(True), "i", "info"),
    )
    assert spec.equations == (Equation("error", x),)  # a stream named like a severity
    assert spec.triggers[1].pos == Pos(3, 1)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("x.aggregate(over: 5s, using: count)", Aggregate(x, 5_000_000_000, "count")),
        ("x.aggregate(using: sum, over: 500ms)", Aggregate(x, 500_000_000, "sum")),
        ("x.aggregate(over: 2.5s, using: avg)", Aggregate(x, 2_500_000_000, "avg")),
        ("x.aggregate(over: 1min, using: min)", Aggregate(x, 60_000_000_000, "min")),
        ("x.aggregate(over: 250us, using: max)", Aggregate(x, 250_000, "max")),
        ("timeout(x, 2s)", Call("timeout", (x, Lit(2_000_000_000)))),
        ("timeout(x, 1h)", Call("timeout", (x, Lit(3_600_000_000_000)))),
        (
            "x.aggregate(over: 5s, using: avg) > 1.0",
            B(">", Aggregate(x, 5_000_000_000, "avg"), Lit(1.0)),
        ),
    ],
)
def test_aggregates_and_timeouts(text: str, expected: ast.Expr) -> None:
    assert parse_expr(text) == expected


# -- errors ----------------------------------------------------------------------------

ERRORS = [
    # (spec, line, col, in the message, in the hint)
    ("in x: Integer", 1, 7, "unknown type 'Integer'", "did you mean Int?"),
    ("in x: String", 1, 7, "unknown type 'String'", "did you mean Str?"),
    ("in x: Lisst<Int>", 1, 7, "unknown type 'Lisst'", "did you mean List?"),
    ("in x: List Int", 1, 12, "expected '<' after List, found 'Int'", "List<T>"),
    ("in x: Struct<a Int>", 1, 16, "expected ':' after the field name 'a'", "Struct<a: T>"),
    ("in x: Map<Int, Int>", 1, 11, "map keys must be Str", "Map<T>"),
    ('out y\ny = "abc', 2, 5, 'unterminated string "abc', 'close it with "'),
    ("out y\ny = if x 1 else 2", 2, 10, "expected 'then' after the condition of 'if'", "then"),
    ("out y\ny = if x then 1", 2, 16, "expected 'else'", "both branches"),
    ("out y\ny = x[2, 0]", 2, 7, "future offset in 'x[2, 0]'", "x[-2, 0]"),
    ("out y\ny = x[1, a + 1]", 2, 7, "future offset", "x[-1, a + 1]"),
    ("out y\ny = x[n]", 2, 7, "offset must be an integer literal, found 'n'", "x[1]"),
    ("out y\ny = x[1.5]", 2, 7, "integer literal, found '1.5'", "x[1]"),
    ("out y\ny = x +", 2, 8, "expected an expression, found the end", "operand"),
    ("out y\ny = (x + 1", 2, 11, "expected ',' or ')'", "close the '(' opened at 2:5"),
    ("out y\ny = [1, 2", 2, 10, "expected ',' or ']' in a list", "','"),
    ("out y\ny = 1 2", 2, 7, "unexpected '2' after the end of the statement", "operator"),
    ("out y\ny = x = 1", 2, 7, "unexpected '='", "'=='"),
    ("out y\ny = == 1", 2, 5, "expected an expression, found '=='", "operand"),
    ("in out", 1, 4, "expected a stream name after 'in', found 'out'", "keyword"),
    ("in x @ 10Hz", 1, 6, "input 'x' cannot have a rate", "out y @ 10Hz"),
    ("out y @ fast", 1, 9, "expected a rate after '@'", "Hz"),
    ("out y\ny = x & z", 2, 7, "unexpected character '&'", "'&&'"),
    ("out y\ny = 'a'", 2, 5, "'a' is in single quotes", 'double quotes: "a"'),
    ("out y\ny = x # 1", 2, 7, "unexpected character '#'", "remove it"),
    ("in x (* never closed\nout y", 1, 6, "unterminated comment", "'*)'"),
    ('out y\ny = "a\\qb"', 2, 7, "unknown escape '\\q'", "\\n"),
    ("out y\ny = x.aggregate(over: 5, using: avg)", 2, 23, "'5' has no unit", "5s"),
    ("out y\ny = x.aggregate(over: 5s, using: median)", 2, 34, "unknown aggregate", "avg"),
    ("out y\ny = x.aggregate(over: 5s)", 2, 7, "needs 'using:'", "using: count"),
    ("out y\ny = x.aggregate(by: 5s)", 2, 17, "unknown argument 'by'", "over: 5s"),
    ("out y\ny = timeout(x, 2sec)", 2, 16, "unknown time unit 'sec'", "500ms"),
    ("out y\ny = timeout(x, 0s)", 2, 16, "longer than zero", "2.5s"),
    ("out y\ny = x + 5s", 2, 9, "duration '5s' cannot be a value", "timeout(x, 2s)"),
    ("out y\ny = 3abc", 2, 5, "unexpected '3abc'", "cannot start with a digit"),
    ('in x\ntrigger x "m" fatal', 2, 15, "unknown severity 'fatal'", "critical"),
    ("in x\ntrigger x", 2, 10, "expected the trigger's message", '"message"'),
    ("out y\ny = 9223372036854775808", 2, 5, "does not fit in 64 bits", "Float"),
    ("out y\ny = -9223372036854775809", 2, 6, "does not fit in 64 bits", "Float"),
    ("x: Int", 1, 1, "expected a declaration or an equation, found 'x'", "in x: T"),
    ("+ 1", 1, 1, "expected a declaration or an equation", "equations (y = x + 1)"),
    ("out y\ny = s.len(1)", 2, 7, "'len(...)' is not a method", "List.len(l)"),
    ("out y\ny = s.(1)", 2, 7, "expected a field name after '.'", "t.0"),
    ("out y\ny = Map(k: 1)", 2, 9, "expected a key in Map(...)", 'Map("k": 1)'),
    ("out y\ny = eval(s, x)", 2, 13, "expected '{' to open the scope", "{x, y}"),
    ("out y\ny = then", 2, 5, "found 'then'", "if c then a else b"),
]


@pytest.mark.parametrize(("text", "line", "col", "message", "hint"), ERRORS)
def test_syntax_errors(text: str, line: int, col: int, message: str, hint: str) -> None:
    (p,) = problems(text)
    assert (p.path, p.line, p.col) == ("t.lola", line, col), str(p)
    assert message in p.message
    assert hint in p.hint
    assert p.text == text.splitlines()[line - 1]


def test_error_message_renders_file_line_col_caret_and_hint() -> None:
    with pytest.raises(SpecError) as info:
        parse_spec("in x: Int\nout y\ny = if x 1 else 2", "specs/a.lola")
    text = str(info.value)
    assert text.startswith("specs/a.lola:3:10: expected 'then'")
    assert "    y = if x 1 else 2\n             ^" in text
    assert "hint:" in text


def test_several_errors_are_reported_at_once_and_good_lines_survive() -> None:
    text = (
        "in x: Integer\n"  # 1: bad type
        "out y\n"
        "y = x[2, 0]\n"  # 3: future offset
        "out z\n"
        "z = x + 1\n"  # fine
        "out w\n"
        "w = if x 1\n"  # 7: no then
        "    else 2\n"
        'trigger z "m" fatal\n'  # 9: bad severity
        "out v\n"
        "v = z\n"
    )
    got = [(p.line, p.col) for p in problems(text)]
    assert got == [(1, 7), (3, 7), (7, 10), (9, 15)]


def test_lexical_error_suppresses_parser_noise_on_its_line() -> None:
    got = problems('out y\ny = "abc\nout z\nz = 1 1')
    assert [(p.line, p.message.split(" ")[0]) for p in got] == [
        (2, "unterminated"),
        (4, "unexpected"),
    ]


def test_parse_expr_errors() -> None:
    with pytest.raises(SpecError) as info:
        parse_expr("x + 1 y", "<eval of s>")
    (p,) = info.value.problems
    assert (p.path, p.line, p.col) == ("<eval of s>", 1, 7)
    assert "unexpected 'y' after the expression" in p.message
    with pytest.raises(SpecError, match="found nothing"):
        parse_expr("   ")
    with pytest.raises(SpecError, match="unterminated string"):
        parse_expr('"abc')


# -- properties ------------------------------------------------------------------------

_OPS: list[ast.BinOp] = [
    "++",
    "=>",
    "||",
    "&&",
    "==",
    "<",
    "<=",
    ">",
    ">=",
    "+",
    "-",
    "*",
    "/",
    "%",
]
_BP = {
    "++": 1,
    "=>": 2,
    "||": 3,
    "&&": 4,
    "==": 5,
    "<": 6,
    "<=": 6,
    ">": 6,
    ">=": 6,
    "+": 7,
    "-": 7,
    "*": 8,
    "/": 8,
    "%": 8,
}

_leaves = st.one_of(
    st.integers(min_value=INT_MIN, max_value=INT_MAX).map(Lit),
    st.integers(-400, 400).map(lambda i: Lit(i / 4)),
    st.booleans().map(Lit),
    st.text(alphabet='ab \n\t"\\', max_size=5).map(Lit),
    st.sampled_from(["a", "b", "speed", "x_1"]).map(Var),
)


def _extend(children: st.SearchStrategy[ast.Expr]) -> st.SearchStrategy[ast.Expr]:
    return st.one_of(
        st.builds(Binary, st.sampled_from(_OPS), children, children),
        st.builds(Unary, st.sampled_from(["-", "!"]), children),
        st.builds(If, children, children, children),
        st.builds(Index, st.sampled_from([Var("a"), Var("b")]), st.integers(0, 5)),
    )


_exprs = st.recursive(_leaves, _extend, max_leaves=12)


def _lit_text(v: object) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        esc = {"\n": "\\n", "\t": "\\t", '"': '\\"', "\\": "\\\\"}
        return '"' + "".join(esc.get(ch, ch) for ch in v) + '"'
    return repr(v)


def _full(e: ast.Expr) -> str:
    """Every compound subexpression in parentheses."""
    match e:
        case Lit(value=v):
            return _lit_text(v)
        case Var(name=n):
            return n
        case Index(expr=inner, offset=k):
            return f"{_full(inner)}[{k}]"
        case Unary(op=op, operand=o):
            return f"({op}({_full(o)}))"
        case Binary(op=op, left=left, right=right):
            return f"({_full(left)} {op} {_full(right)})"
        case If(cond=cond, then=then, else_=other):
            return f"(if {_full(cond)} then {_full(then)} else {_full(other)})"
    raise AssertionError(e)


def _min(e: ast.Expr) -> tuple[str, int]:
    """As few parentheses as the precedence table allows; returns (text, binding power)."""
    match e:
        case Lit(value=v):
            return _lit_text(v), 100
        case Var(name=n):
            return n, 100
        case Index(expr=inner, offset=k):
            return f"{_min(inner)[0]}[{k}]", 100
        case Unary(op=op, operand=o):
            text, bp = _min(o)
            if bp < 9 or (isinstance(o, Lit) and type(o.value) in (int, float)):
                text = f"({text})"  # a parenthesised literal is not folded into Lit(-n)
            return f"{op} {text}", 9
        case Binary(op=op, left=left, right=right):
            p = _BP[op]
            lt, lbp = _min(left)
            rt, rbp = _min(right)
            if lbp < p or (lbp == p and op == "=>"):
                lt = f"({lt})"
            if rbp < p or (rbp == p and op != "=>"):
                rt = f"({rt})"
            return f"{lt} {op} {rt}", p
        case If(cond=cond, then=then, else_=other):
            return f"if {_min(cond)[0]} then {_min(then)[0]} else {_min(other)[0]}", 0
    raise AssertionError(e)


@settings(max_examples=150, deadline=None)
@given(_exprs)
def test_fully_parenthesised_text_parses_back_to_the_tree(e: ast.Expr) -> None:
    assert parse_expr(_full(e)) == e


@settings(max_examples=150, deadline=None)
@given(_exprs)
def test_minimally_parenthesised_text_parses_back_to_the_tree(e: ast.Expr) -> None:
    assert parse_expr(_min(e)[0]) == e


_types = st.recursive(
    st.sampled_from([INT, FLOAT, STR, BOOL, TName("Unit"), ast.TAny]),
    lambda ts: st.one_of(
        ts.map(TList),
        ts.map(TMap),
        st.lists(st.tuples(st.sampled_from(["a", "b", "c"]), ts), min_size=1, max_size=3).map(
            lambda fs: TStruct(tuple(fs))
        ),
        st.lists(ts, min_size=2, max_size=3).map(lambda xs: TTuple(tuple(xs))),
    ),
    max_leaves=8,
)


@settings(max_examples=100, deadline=None)
@given(_types)
def test_types_print_and_parse_back(t: ast.Type) -> None:
    assert parse_spec(f"in x: {t}").decls[0].type == t


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("(" * 150 + "1" + ")" * 150, "nested more than 100 levels deep"),
        ("!" * 150 + "a", "more than 100 unary operators in a row"),
        (" + ".join(["a"] * 300), "expression is 300 levels deep, more than 250"),
        ("[" * 150 + "]" * 150, "nested more than 100 levels deep"),
        (" => ".join(["a"] * 900), "nested more than 100 levels deep"),
        ("if a then " * 150 + "1" + " else 2" * 150, "nested more than 100 levels deep"),
    ],
)
def test_pathological_nesting_is_a_spec_error_not_a_crash(text: str, message: str) -> None:
    with pytest.raises(SpecError, match=message):
        parse_expr(text)
    with pytest.raises(SpecError, match=message):
        parse_spec(f"out y\ny = {text}")


def test_deep_but_allowed_expressions_parse() -> None:
    e = parse_expr(" + ".join(["a"] * 200))
    assert isinstance(e, Binary)
    assert parse_expr("(" * 60 + "1" + ")" * 60) == Lit(1)


def test_the_deepest_allowed_trees_check_without_recursion_errors() -> None:
    chain = " + ".join(["x"] * 249)
    calls = "default(" * 95 + "x" + ", 1)" * 95
    spec = parse_spec(f"in x: Int\nout y: Int\nout z: Int\ny = {chain}\nz = {calls}")
    assert check_spec(spec) == []
    bad = parse_spec(f"in x: Int\nout y: Int\ny = {chain} + true")
    assert len(check_spec(bad)) == 1


def test_recovery_keeps_a_statement_the_broken_one_ran_into() -> None:
    got = problems("out y\ny = x +\nout z: Integer\nz = 1")
    assert [(p.line, p.col) for p in got] == [(3, 1), (3, 8)]
    assert "expected an expression, found 'out'" in got[0].message
    assert "unknown type 'Integer'" in got[1].message
