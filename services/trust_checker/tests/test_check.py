"""Static checks: declarations, names, functions, types, cycles, memory; load_spec."""

from __future__ import annotations

import dataclasses
import pathlib

import pytest
import trust_checker.lang as lang
from trust_checker.errors import Problem, SpecError
from trust_checker.lang import (
    Limits,
    check_spec,
    dependency_order,
    load_spec,
    memory_bound,
    parse_spec,
)

HEADER = """\
in x: Int
in f: Float
in s: Str
in b: Bool
in l: List<Int>
in m: Map<Int>
in st: Struct<a: Int, bb: Str>
in tp: (Int, Bool)
in anything: Any
in untyped
"""
HEADER_LINES = HEADER.count("\n")


DEFAULT = Limits()


def check(text: str, limits: Limits = DEFAULT) -> list[Problem]:
    return check_spec(parse_spec(text, "c.dsrv"), limits)


def one(text: str) -> Problem:
    got = check(text)
    assert len(got) == 1, "\n".join(map(str, got))
    return got[0]


GOOD = """\
in x: Int
in s: Str
out count: Int
out high: Bool
aux total: Float
out e: Int
out label: Str
count = default(count[1], 0) + 1
total = x + 1.5
high = total > 3.0 && when(x) || !is_defined(x[2])
e = eval(s: Int, {x, count})
label = if high then "high" else s ++ "!"
trigger high "too high" critical
"""


def test_a_good_spec_has_no_problems() -> None:
    assert check(GOOD) == []


def test_limits_defaults_and_frozen() -> None:
    lim = Limits()
    assert (lim.max_history_slots, lim.dynamic_history, lim.window_samples) == (
        1_000_000,
        64,
        10_000,
    )
    with pytest.raises(dataclasses.FrozenInstanceError):
        lim.dynamic_history = 1  # type: ignore[misc]


# -- declarations and equations ---------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "line", "col", "message", "hint"),
    [
        ("in x\nout y", 2, 1, "output 'y' has no equation", "add one: y = EXPR"),
        ("in x\naux y", 2, 1, "aux stream 'y' has no equation", "y = EXPR"),
        ("in x\nx = 1", 2, 1, "input 'x' has an equation", "declare it out or aux"),
        ("out y\ny = 1\ny = 2", 3, 1, "'y' has a second equation (the first is at 2:1)", "if"),
        ("in x\nin x", 2, 1, "stream 'x' is declared twice (first at 1:1)", "remove one"),
        ("in x\ny = x", 2, 1, "equation for 'y', which is not declared", "declare it: out y: T"),
        ("in speed\nout y\ny = sped + 1", 3, 5, "unknown stream 'sped'", "did you mean 'speed'?"),
        ("out y\ny = zzz", 2, 5, "unknown stream 'zzz'", "declare it: in zzz: T"),
        ("in s: Str\nout y\ny = eval(s, {s, q})", 3, 5, "unknown stream 'q'", "in q: T"),
        (
            "in x\nout y\ny = defualt(x, 1)",
            3,
            5,
            "unknown function 'defualt'",
            "did you mean default?",
        ),
        ("in x\nout y\ny = List.lenght(x)", 3, 5, "unknown function 'List.lenght'", "List.len"),
        (
            "in x\nout y\ny = default(x)",
            3,
            5,
            "'default' takes 2 arguments, found 1",
            "default(e, d)",
        ),
        ("in x\nout y\ny = sin(x, x)", 3, 5, "'sin' takes 1 argument, found 2", "sin(x)"),
        (
            "in x\nout y\ny = Map.insert(x, 1)",
            3,
            5,
            "takes 3 arguments",
            "Map.insert(map, key, value)",
        ),
    ],
)
def test_declaration_and_name_problems(
    text: str, line: int, col: int, message: str, hint: str
) -> None:
    p = one(text)
    assert (p.path, p.line, p.col) == ("c.dsrv", line, col), str(p)
    assert message in p.message
    assert hint in p.hint
    assert p.text == text.splitlines()[line - 1]


def test_every_problem_is_reported_sorted() -> None:
    got = check("in x\nout y\nout z\nz = q + w\nx = 1")
    assert [(p.line, p.col) for p in got] == [(2, 1), (4, 5), (4, 9), (5, 1)]


# -- types -----------------------------------------------------------------------------

TYPE_ERRORS = [
    # (equation for `out y` / `out y: T`, col in the equation line, message, hint)
    ("y = x + s", 9, "the right operand of '+' must be Int or Float, found Str", "'++'"),
    ("y = b * 2", 5, "the left operand of '*' must be Int or Float, found Bool", ""),
    ("y = s ++ x", 10, "the right operand of '++' must be Str, found Int", ""),
    ("y = x && true", 5, "the left operand of '&&' must be Bool, found Int", ""),
    ("y = b => 1", 10, "the right operand of '=>' must be Bool, found Int", ""),
    ("y = !x", 6, "the operand of '!' must be Bool, found Int", ""),
    ("y = -s", 6, "the operand of '-' must be Int or Float, found Str", ""),
    ("y = x == s", 7, "'==' compares Int with Str", "same type"),
    ("y = x != b", 7, "'==' compares Int with Bool", "same type"),
    ("y = s < x", 7, "'<' compares Str with Int", "numbers with numbers"),
    ("y = l > 1", 5, "the left operand of '>' must be Int, Float or Str, found List<Int>", ""),
    ("y = if x then 1 else 2", 8, "the condition of 'if' must be Bool, found Int", ""),
    ("y = if b then 1 else 2.0", 22, "the branches of 'if' differ: Int and Float", "same type"),
    ("y = default(x, s)", 16, "the arguments of default(...) differ: Int and Str", ""),
    ("y = List.get(m, 0)", 14, "the first argument of List.get must be a List, found Map<Int>", ""),
    ("y = List.get(l, s)", 17, "the index of List.get must be Int, found Str", ""),
    ("y = List.append(l, s)", 20, "differ: Int and Str", ""),
    ("y = List.concat(l, [s])", 20, "differ: Int and Str", ""),
    ("y = Map.get(m, 1)", 16, "the key of Map.get must be Str, found Int", ""),
    ('y = Map.insert(m, "k", b)', 24, "differ: Int and Bool", ""),
    ("y = st.c", 8, "Struct<a: Int, bb: Str> has no field 'c'", "'a'"),
    ("y = st.b", 8, "has no field 'b'", "did you mean 'bb'?"),
    ("y = tp.2", 8, "(Int, Bool) has no item 2", "from 0 to 1"),
    ("y = x.a", 7, "the value before '.a' must be a struct, found Int", ""),
    ('y = [1, "a"]', 9, "the items of a list differ: Int and Str", ""),
    ('y = Map("k": 1, "j": true)', 22, "the values of a map differ", ""),
    ("y = {a: 1, a: 2}", 5, "field 'a' appears twice", ""),
    ("y = eval(x)", 10, "the source of eval(...) must be Str, found Int", ""),
    ("y = s.aggregate(over: 1s, using: sum)", 5, "aggregate(using: sum) must be Int or Float", ""),
    ("y = sin(s)", 9, "the argument of sin must be Int or Float, found Str", ""),
]


@pytest.mark.parametrize(("equation", "col", "message", "hint"), TYPE_ERRORS)
def test_type_errors_point_at_the_subexpression(
    equation: str, col: int, message: str, hint: str
) -> None:
    p = one(f"{HEADER}out y\n{equation}")
    assert (p.line, p.col) == (HEADER_LINES + 2, col), str(p)
    assert p.message.startswith("type error: ")
    assert message in p.message
    assert hint in p.hint


@pytest.mark.parametrize(
    ("decl", "equation"),
    [
        ("out y: Float", "y = x + f"),  # Int with Float is Float
        ("out y: Float", "y = f * 2"),
        ("out y: Int", "y = x / 2 % 3 - -x"),
        ("out y: Bool", "y = x == f"),  # numbers compare across Int and Float
        ("out y: Bool", 'y = s < "b" && x >= f'),
        ("out y: Str", 'y = s ++ "!"'),
        ("out y: Float", "y = sin(x) + abs(f)"),
        ("out y: Int", "y = abs(x)"),
        ("out y: List<Int>", "y = List.append(List.tail(l), List.len(l))"),
        ("out y: List<Int>", "y = List.concat(l, [1, 2])"),
        ("out y: List<Int>", "y = []"),
        ("out y: Int", "y = List.get(l, 0) + List.head(l)"),
        ("out y: Map<Int>", 'y = Map.remove(Map.insert(m, "k", 1), "j")'),
        ("out y: Bool", 'y = Map.has_key(m, "k") && Map.get(m, "k") > 0'),
        ("out y: Struct<a: Int, bb: Str>", 'y = {a: 1, bb: "x"}'),
        ("out y: Struct<a: Int, bb: Str>", "y = st"),
        ("out y: (Int, Bool)", "y = (st.a, tp.1)"),
        ("out y: Int", "y = tp.0"),
        ("out y: Int", "y = untyped + anything"),  # unknown types pass
        ("out y: Bool", "y = untyped && anything.field.deeper"),
        ("out y: Int", "y = latch(x, b) + update(1, x) + init(x[1], 0)"),
        ("out y: Bool", "y = when(s) || is_defined(x)"),
        ("out y: Int", "y = eval(s: Int)"),
        ("out y: Int", "y = eval(s) + 1"),  # unascribed eval is unknown
        ("out y: Int", "y = x.aggregate(over: 1s, using: count)"),
        ("out y: Float", "y = x.aggregate(over: 1s, using: avg)"),
        ("out y: Int", "y = x.aggregate(over: 1s, using: max)"),
        ("out y: Bool", "y = timeout(x, 2s)"),
        ("out y: Unit", "y = ()"),
        ("out y: Any", "y = if b then 1 else 2"),
        ("out y", "y = if b then untyped else s"),  # an unknown branch agrees with any
    ],
)
def test_well_typed_equations(decl: str, equation: str) -> None:
    got = check(f"{HEADER}{decl}\n{equation}")
    assert got == [], "\n".join(map(str, got))


@pytest.mark.parametrize(
    ("decl", "equation", "found", "hint"),
    [
        ("out y: Int", "y = x + 1.5", "Float", "change the declared type"),
        ("out y: Float", "y = x + 1", "Int", "an Int is not a Float"),
        ("out y: Bool", "y = x", "Int", ""),
        ("out y: List<Str>", "y = l", "List<Int>", ""),
        ("out y: Struct<a: Int>", "y = {b: 1}", "Struct<b: Int>", ""),
    ],
)
def test_equation_must_give_the_declared_type(
    decl: str, equation: str, found: str, hint: str
) -> None:
    p = one(f"{HEADER}{decl}\n{equation}")
    name_type = decl.split(": ", 1)[1]
    assert f"'y' is declared {name_type} but its equation gives {found}" in p.message
    assert hint in p.hint


def test_trigger_condition_must_be_bool() -> None:
    p = one('in x: Int\ntrigger x + 1 "m"')
    assert (p.line, p.col) == (2, 11)
    assert "the condition of a trigger must be Bool, found Int" in p.message


# -- cycles ----------------------------------------------------------------------------


def test_named_zero_weight_cycle() -> None:
    p = one("in x: Int\nout a: Int\nout b: Int\na = b + x\nb = a * 2")
    assert "zero-weight cycle a -> b -> a" in p.message
    assert "needs the others at the same tick" in p.message
    assert "break it with an offset, e.g. b[1]" in p.hint
    assert (p.line, p.col) == (4, 5)  # the reference to b in a's equation


def test_self_cycle_and_longer_cycle() -> None:
    (p,) = check("in x\nout a\na = a + x")
    assert "zero-weight cycle a -> a" in p.message
    (q,) = check("out a\nout b\nout c\na = c\nb = a\nc = b + 1")
    assert "zero-weight cycle a -> c -> b -> a" in q.message


@pytest.mark.parametrize(
    "spec",
    [
        "in x\nout a\nout b\na = b[1] + x\nb = a",  # an offset breaks it
        "in x\nout a\nout b\na = b[-1, 0] + x\nb = a",  # D5.2 form
        "in x\nout a\na = default(a[1], 0) + x",  # the classic counter
        "in x\nout a\nout b\na = (b + x)[2]\nb = a",  # offsets apply inside index
        "in s: Str\nout y: Int\ny = eval(s, {y})",  # eval refers to its source only
    ],
)
def test_cycles_that_are_fine(spec: str) -> None:
    assert check(spec) == []


def test_eval_of_its_own_stream_is_a_cycle() -> None:
    (p,) = check("out s: Str\ns = defer(s)")
    assert "zero-weight cycle s -> s" in p.message


def test_dependency_order() -> None:
    spec = parse_spec("in x\nout c\nout b\naux a\nout d\nc = b + a\nb = a * 2\na = x + d[1]\nd = c")
    order = dependency_order(spec)
    assert order == ["a", "b", "c", "d"]
    assert dependency_order(parse_spec("in x\nout p\nout q\np = x\nq = x")) == ["p", "q"]
    with pytest.raises(SpecError, match="zero-weight cycle a -> b -> a"):
        dependency_order(parse_spec("out a\nout b\na = b\nb = a"))


# -- memory bound ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("spec", "slots"),
    [
        ("in x\nout y\ny = x", 0),
        ("in x\nin z\nout y\ny = x[3] + x[5] + z[2]", 7),
        ("in x\nout y\ny = (x[2])[3]", 5),
        ("in x\nout y\ny = x[-4, 0]", 4),
        ('in x\nout y\ny = x[1]\ntrigger x[9] > 1 "m"', 9),
        ("in s: Str\nout y\ny = eval(s) + s[2]", 2 + 64 * 2),
        ("in x\nout y\ny = x.aggregate(over: 1s, using: sum)", 10_000),
        (
            "in x\nout y\n"
            "y = x.aggregate(over: 1s, using: sum) + x.aggregate(over: 2s, using: max)",
            20_000,
        ),
    ],
)
def test_memory_bound(spec: str, slots: int) -> None:
    assert memory_bound(parse_spec(spec)) == slots


def test_memory_bound_follows_the_limits() -> None:
    spec = parse_spec("in s: Str\nout y\ny = eval(s).aggregate(over: 1s, using: count)")
    assert memory_bound(spec, Limits(dynamic_history=10, window_samples=7)) == 10 * 2 + 7


def test_memory_over_the_limit_is_an_error() -> None:
    p = one("in x\nout y\ny = x + x[2000000]")
    assert "needs 2000000 history slots, more than the limit of 1000000" in p.message
    assert "x[2000000]" in p.message
    assert (p.line, p.col) == (3, 10)
    assert "max_history_slots" in p.hint
    small = Limits(max_history_slots=3)
    assert check("in x\nout y\ny = x[3]", small) == []
    (q,) = check("in x\nout y\ny = x[4]", small)
    assert "needs 4 history slots" in q.message


# -- load_spec -------------------------------------------------------------------------


def test_load_spec_from_text_path_and_file_name(tmp_path: pathlib.Path) -> None:
    spec = load_spec(GOOD)
    assert spec.outputs == ("count", "high", "e", "label")
    assert spec.path == "<spec>"
    f = tmp_path / "good.dsrv"
    f.write_text(GOOD, encoding="utf-8")
    assert load_spec(f) == spec
    assert load_spec(f).path == str(f)
    assert load_spec(f, path="named").path == "named"
    assert load_spec("in x\nout y\ny = x", path="inline").path == "inline"


def test_load_spec_raises_every_problem() -> None:
    with pytest.raises(SpecError) as info:
        load_spec("in x: Int\nout y: Bool\nout z\ny = x + 1\nz = q", path="bad.dsrv")
    got = [(p.path, p.line, p.col) for p in info.value.problems]
    assert got == [("bad.dsrv", 4, 7), ("bad.dsrv", 5, 5)]
    with pytest.raises(SpecError, match="unknown type 'Integer'"):
        load_spec("in x: Integer")
    with pytest.raises(SpecError, match="needs 5 history slots"):
        load_spec("in x\nout y\ny = x[5]", limits=Limits(max_history_slots=4))


def test_load_spec_never_opens_a_str(tmp_path: pathlib.Path) -> None:
    f = tmp_path / "good.dsrv"
    f.write_text(GOOD, encoding="utf-8")
    with pytest.raises(SpecError, match="expected a declaration or an equation"):
        load_spec(str(f))  # a str is spec text: network input can never name a file


def test_exports() -> None:
    assert set(lang.__all__) == {
        "Limits",
        "check_spec",
        "dependency_order",
        "load_spec",
        "memory_bound",
        "parse_expr",
        "parse_spec",
        "read_source",
    }
    for name in lang.__all__:
        assert getattr(lang, name) is not None
