"""The evaluator's fast paths (trust_checker.engine.lifted: typed operators, comparisons fused
into their parent, ``if`` chains as tables, ``x[k]`` defaults, skipped streams) give what
the general path gives, on values of every type, at the edges (64-bit overflow, NaN,
-0.0, infinities) and off the declared types (values of another type, ⊥)."""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from trust_checker import operators as op
from trust_checker.engine import SpecRunner
from trust_checker.errors import EvalError
from trust_checker.lang import load_spec
from trust_checker.values import BOTTOM, INT_MAX, INT_MIN, console

SETTINGS = settings(max_examples=40, deadline=None)

INTS = st.one_of(
    st.integers(-20, 20), st.sampled_from([INT_MIN, INT_MAX, INT_MAX - 1, 2**32, -(2**32)])
)
FLOATS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([0.0, -0.0, 1.5])
)
VALUES: dict[str, Any] = {
    "Int": INTS,
    "Float": FLOATS,
    "Str": st.sampled_from(["", "a", "b", "ab"]),
    "Bool": st.booleans(),
}
OPS = ["+", "-", "*", "==", "!=", "<", "<=", ">", ">=", "&&", "||", "=>", "++"]


def _expected(o: str, a: object, b: object) -> str:
    if a is BOTTOM or b is BOTTOM:
        return "Deferred"
    try:
        if o == "!=":
            return console(op.logical_not(op.equal(a, b)))
        return console(op.BINARY[o](a, b))
    except op.Fault:
        return "error"


def _got(m: SpecRunner, inputs: dict[str, object]) -> str:
    try:
        outs = m.step(inputs)
    except EvalError:
        return "error"
    (out,) = outs
    return console(out.value)


def _typed(o: str, ta: str, tb: str) -> bool:
    """Whether the checker takes ``a o b`` on these types."""
    if o in ("&&", "||", "=>"):
        return ta == tb == "Bool"
    if o == "++":
        return ta == tb == "Str"
    if o in ("+", "-", "*"):
        return "Bool" not in (ta, tb) and "Str" not in (ta, tb)
    if o in ("<", "<=", ">", ">="):
        return "Bool" not in (ta, tb)
    return True


@pytest.mark.parametrize(
    ("o", "ta", "tb"),
    [
        (o, ta, tb)
        for o in OPS
        for ta, tb in [(t, t) for t in VALUES] + [("Int", "Float"), ("Float", "Int")]
        if _typed(o, ta, tb)
    ],
)
@SETTINGS
@given(data=st.data())
def test_binary_operators_on_declared_types(o: str, ta: str, tb: str, data: Any) -> None:
    spec = load_spec(f"in a: {ta}\nin b: {tb}\nout r\nr = a {o} b\n")
    m = SpecRunner(spec)
    for _ in range(4):
        a = data.draw(st.one_of(VALUES[ta], st.just(BOTTOM)))
        b = data.draw(st.one_of(VALUES[tb], st.just(BOTTOM)))
        a = float(a) if ta == "Float" and type(a) is int else a
        b = float(b) if tb == "Float" and type(b) is int else b
        assert _got(m, {"a": a, "b": b}) == _expected(o, a, b), (a, o, b)


@SETTINGS
@given(st.lists(st.one_of(st.integers(-3, 3), st.just(INT_MAX), st.booleans(), st.text("ab"))))
def test_untyped_streams_take_the_general_path(values: list[object]) -> None:
    m = SpecRunner(load_spec("in a\nin b: Int\nout r\nout e\nr = a + b\ne = a == 1\n"))
    for v in values:
        try:
            outs = {o.stream: console(o.value) for o in m.step({"a": v, "b": 1})}
        except EvalError:
            outs = {"r": "error"}
        try:
            want = console(op.add(v, 1))
        except op.Fault:
            want = "error"
        assert outs["r"] == want
        if "e" in outs:
            assert outs["e"] == console(op.equal(v, 1))


@SETTINGS
@given(st.lists(st.sampled_from(["monitor", "plan", "execute", "x", ""]), min_size=1))
def test_an_if_chain_on_one_stream_is_a_table(stages: list[str]) -> None:
    m = SpecRunner(
        load_spec(
            'in s: Str\nout r: Int\nr = if s == "monitor" then 0 else if s == "plan" '
            'then 2 else if "monitor" == s then 9 else -1\n'
        )
    )
    table = {"monitor": 0, "plan": 2}
    for s in stages:
        (out,) = m.step({"s": s})
        assert out.value == table.get(s, -1)
    (out,) = m.step({"s": BOTTOM})
    assert out.value is BOTTOM


@SETTINGS
@given(
    st.lists(
        st.fixed_dictionaries(
            {}, optional={"a": st.integers(-2, 2), "b": FLOATS, "c": st.booleans()}
        ),
        max_size=30,
    )
)
def test_fused_comparisons_and_skipped_streams_match_python(ticks: list[dict[str, Any]]) -> None:
    m = SpecRunner(
        load_spec(
            "in a: Int\nin b: Float\nin c: Bool\nout x: Bool\nout y: Int\nout z: Int\n"
            "x = a == 1 && b < 2.5 || !c\ny = default(a[2], 7) + a\nz = 3 * 4 - 1\n"
        )
    )
    held: dict[str, Any] = {}
    hist: list[Any] = [None, None]
    for t in ticks:
        held.update(t)
        got = {o.stream: o.value for o in m.step(t)}
        a, b, c = held.get("a"), held.get("b"), held.get("c")
        if a is not None and b is not None and c is not None:
            want = (a == 1 and b < 2.5) or not c
            assert got["x"] is want
        else:
            assert "x" not in got
        if a is not None:
            past = hist[-2]
            assert got["y"] == (7 if past is None else past) + a
        assert got["z"] == 11
        hist.append(a)
