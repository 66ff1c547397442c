"""Trace files: the reference format, literal values, errors at path:line:col."""

from __future__ import annotations

import pytest
from trust_checker.errors import EvalError, InputError
from trust_checker.lang import load_spec
from trust_checker.tracefile import iter_trace, load_trace, read_trace, run_trace
from trust_checker.values import UNIT, MapV, StructV, TupleV


def test_blocks_and_indented_lines() -> None:
    text = "0: x = 1\n   y = 2\n1: x = 3\n"
    assert read_trace(text) == [{"x": 1, "y": 2}, {"x": 3}]


def test_gaps_and_late_first_block_are_empty_ticks() -> None:
    assert read_trace("2: x = 1\n4: x = 2\n") == [{}, {}, {"x": 1}, {}, {"x": 2}]


def test_a_bare_number_is_an_empty_tick() -> None:
    assert read_trace("0:\n1: x = 1\n") == [{}, {"x": 1}]


def test_comments_and_blank_lines() -> None:
    text = '// header\n\n0: s = "a // b"  // trailing\n   // alone\n   t = "\\"//"\n'
    assert read_trace(text) == [{"s": "a // b", "t": '"//'}]


@pytest.mark.parametrize(
    ("literal", "value"),
    [
        ("-3", -3),
        ("1.5", 1.5),
        ("-2.5", -2.5),
        ("true", True),
        ("false", False),
        ('"a\\tb"', "a\tb"),
        ("()", UNIT),
        ("[1, [2]]", (1, (2,))),
        ("List(1, 2)", (1, 2)),
        ('Map("k": 1)', MapV(k=1)),
        ("{a: 1, b: true}", StructV(a=1, b=True)),
        ('Struct("a": 1)', StructV(a=1)),
        ("(1, false)", TupleV((1, False))),
    ],
)
def test_literal_values(literal: str, value: object) -> None:
    (tick,) = read_trace(f"0: v = {literal}\n")
    assert tick["v"] == value
    assert type(tick["v"]) is type(value)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("1: x = 1\n1: x = 2\n", "t.trace:2:1: tick 1 comes after tick 1"),
        ("1: x = 1\n0: x = 2\n", "t.trace:2:1: tick 0 comes after tick 1"),
        ("x = 1\n", "t.trace:1:1: expected 'N: name = value'"),
        ("0: x = 1\ny = 2\n", "t.trace:2:1: expected 'N: name = value' to open a tick - lines"),
        ("0: x = 1\n   x = 2\n", "t.trace:2:4: 'x' is given twice in tick 0"),
        ("0: x == 1\n", "t.trace:1:4: expected 'name = value'"),
        ("0: x = y + 1\n", "t.trace:1:10: a trace value must be a literal"),
        ("0: x = [1, y]\n", "t.trace:1:12: a trace value must be a literal"),
        ("0: x = 1 +\n", "t.trace:1:"),
    ],
)
def test_errors_say_where(text: str, message: str) -> None:
    with pytest.raises(InputError) as err:
        read_trace(text, path="t.trace")
    assert message in str(err.value)


def test_run_trace_prints_console_lines_with_the_drain() -> None:
    spec = load_spec('in x: Int\nout y: Int\ny = x[1]\nout s: Str\ns = "v"\n')
    lines = run_trace(spec, read_trace("0: x = 1\n1: x = 2\n"))
    assert lines == [
        "y[0] = Deferred",
        's[0] = Str("v")',
        "y[1] = Int(1)",
        's[1] = Str("v")',
        "y[2] = Int(2)",
    ]


def test_run_trace_rejects_a_bad_value() -> None:
    spec = load_spec("in x: Int\nout y: Int\ny = x\n")
    with pytest.raises(InputError, match="input 'x' at tick 1: expected Int, got Bool"):
        run_trace(spec, read_trace("0: x = 1\n1: x = true\n"))


def test_iter_trace_gives_each_tick_before_the_one_that_fails() -> None:
    spec = load_spec("in x: Int\nout y: Int\ny = 10 / x\n")
    trace = load_trace("// a trace\n0: x = 5\n2: x = 0\n3: x = 1\n", "t.trace")
    assert trace.lines == [2, 0, 3, 4]
    assert trace.where("t.trace", 2) == "t.trace:3:1"
    assert trace.where("t.trace", 1) == "t.trace"  # a tick no block gives
    ticks = iter_trace(spec, trace.ticks)
    assert [(o.stream, o.value) for o in next(ticks)] == [("y", 2)]
    assert [(o.stream, o.value) for o in next(ticks)] == [("y", 2)]  # held
    with pytest.raises(EvalError, match=r"Int division by zero: 10 / 0 .* in 'y' at tick 2"):
        next(ticks)
