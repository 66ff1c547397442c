"""The evaluator's API and what the golden suite cannot show: inputs and errors, hot swap,
bounded memory, real time (aggregates, timeouts, periodic outputs), triggers, and nodes
that can be inspected."""

from __future__ import annotations

import pytest
from trust_checker.engine import Fired, Output, SpecRunner
from trust_checker.errors import EvalError, InputError, SpecError
from trust_checker.lang import Limits, load_spec
from trust_checker.lang import ast as A
from trust_checker.values import BOTTOM, NOVAL, UNIT, MapV, StructV, TupleV

SEC = 1_000_000_000


def mon(src: str, **kw: object) -> SpecRunner:
    return SpecRunner(load_spec(src, path="t.dsrv"), **kw)  # type: ignore[arg-type]


def vals(outs: list[Output]) -> dict[str, object]:
    return {o.stream: o.value for o in outs}


SUM = "in x: Int\nin y: Int\nout z: Int\nz = x + y\n"


# -- the API -------------------------------------------------------------------------------


def test_step_returns_outputs_with_tick_and_timestamp() -> None:
    m = mon(SUM)
    assert m.step({"x": 1}, ts_ns=5) == []
    assert m.step({"y": 2}, ts_ns=7) == [Output("z", 1, 3, 7)]
    assert m.tick == 2
    assert m.inputs == ("x", "y")
    assert m.outputs == ("z",)
    assert m.spec.outputs == ("z",)


def test_runner_takes_a_hand_built_spec() -> None:
    spec = A.Spec(
        decls=(A.Decl("in", "x", A.TName("Int")), A.Decl("out", "y", A.TName("Int"))),
        equations=(A.Equation("y", A.Binary("*", A.Var("x"), A.Lit(2))),),
        order=("x", "y"),
    )
    m = SpecRunner(spec)
    assert vals(m.step({"x": 21})) == {"y": 42}


def test_a_spec_that_does_not_check_is_rejected() -> None:
    spec = A.Spec(
        decls=(A.Decl("out", "y", A.TName("Int")),),
        equations=(A.Equation("y", A.Var("nope")),),
        order=("y",),
    )
    with pytest.raises(SpecError, match="unknown stream 'nope'"):
        SpecRunner(spec)


def test_unknown_input_is_rejected_and_the_tick_not_taken() -> None:
    m = mon(SUM)
    with pytest.raises(InputError, match=r"unknown input 'q'.*x, y"):
        m.step({"q": 1})
    with pytest.raises(InputError, match="'z' is an out stream"):
        m.step({"z": 1})
    assert m.tick == 0


def test_bad_input_value_is_rejected_and_nothing_changes() -> None:
    m = mon(SUM)
    m.step({"x": 1, "y": 1})
    with pytest.raises(InputError, match=r"input 'x' at tick 1: expected Int, got Str"):
        m.step({"y": 5, "x": "a"})
    assert m.tick == 1
    assert m.held("y") == 1  # y=5 of the refused tick was not taken
    assert vals(m.step({"y": 2})) == {"z": 3}


@pytest.mark.parametrize(
    ("decl", "value", "taken"),
    [
        ("Int", True, None),
        ("Int", 2**63, None),
        ("Float", 3, 3.0),
        ("Bool", 1, None),
        ("List<Int>", (1, 2), (1, 2)),
        ("List<Float>", (1, 2.5), (1.0, 2.5)),
        ("List<Int>", [1], None),
        ("Map<Int>", MapV(a=1), MapV(a=1)),
        ("Struct<a: Int>", StructV(a=1), StructV(a=1)),
        ("Struct<a: Int>", StructV(b=1), None),
        ("(Int, Bool)", TupleV((1, True)), TupleV((1, True))),
        ("Unit", UNIT, UNIT),
        ("Any", "s", "s"),
    ],
)
def test_inputs_conform_to_declared_types(decl: str, value: object, taken: object) -> None:
    m = mon(f"in x: {decl}\nout y: {decl}\ny = x\n")
    if taken is None:
        with pytest.raises(InputError, match="input 'x'"):
            m.step({"x": value})
    else:
        (out,) = m.step({"x": value})
        assert out.value == taken
        assert type(out.value) is type(taken)


def test_noval_input_is_the_same_as_absent() -> None:
    m = mon(SUM)
    assert m.step({"x": 1, "y": NOVAL}) == []
    assert m.held("y") is NOVAL


def test_run_time_error_names_stream_tick_and_place_and_runner_goes_on() -> None:
    m = mon("in a: Int\nin b: Int\nout ok: Int\nout q: Int\nok = a + 1\nq = a / b\n")
    assert vals(m.step({"a": 6, "b": 3})) == {"ok": 7, "q": 2}
    with pytest.raises(EvalError) as err:
        m.step({"b": 0})
    e = err.value
    assert (e.stream, e.tick) == ("q", 1)
    assert e.where == "t.dsrv:6:7"
    assert "division by zero" in str(e)
    assert m.tick == 2  # the tick was taken, its outputs lost
    assert vals(m.step({"b": 2})) == {"ok": 7, "q": 3}


def test_overflow_is_an_error_not_bottom() -> None:
    m = mon("in x: Int\nout y: Int\ny = -x\n")
    with pytest.raises(EvalError, match="Int overflow"):
        m.step({"x": -(2**63)})


def test_finish_is_idempotent_and_step_after_finish_fails() -> None:
    m = mon("in x: Int\nout y: Int\ny = x[2]\n")
    m.step({"x": 1})
    assert [(o.tick, o.value) for o in m.finish()] == [(1, BOTTOM), (2, 1)]
    assert m.finish() == []
    with pytest.raises(InputError, match="finished"):
        m.step({"x": 1})


def test_float_output_widens_int_values() -> None:
    m = mon("in x: Int\nout y: Float\ny = x + 0.0\nout z: Float\nz = 2.0 * 1\n")
    out = vals(m.step({"x": 1}))
    assert out == {"y": 1.0, "z": 2.0}
    assert all(type(v) is float for v in out.values())


# -- bounded memory ----------------------------------------------------------------------------


def test_history_is_as_deep_as_the_largest_offset() -> None:
    m = mon("in x: Int\nin w: Int\nout y: Int\ny = x[3] + x[1]\nout v: Int\nv = w\n")
    streams = m._streams
    assert streams["x"].hist is not None
    assert streams["x"].hist.maxlen == 3
    assert streams["w"].hist is None
    assert streams["y"].hist is None
    for i in range(1000):
        m.step({"x": i})
    assert len(streams["x"].hist) == 3


def test_eval_keeps_dynamic_history_for_every_stream() -> None:
    m = mon("in s: Str\nin x: Int\nout y: Int\ny = eval(s)\n", limits=Limits(dynamic_history=5))
    assert m._streams["x"].hist.maxlen == 5  # type: ignore[union-attr]
    for i in range(10):
        m.step({"x": i})
    assert vals(m.step({"s": "x[5]", "x": 10})) == {"y": 5}
    with pytest.raises(EvalError, match=r"x\[6\] reaches further back than the 5 ticks"):
        m.step({"s": "x[6]"})


def test_index_of_an_expression() -> None:
    m = mon("in x: Int\nin y: Int\nout z: Int\nz = (x + y)[1]\n")
    assert m.step({"x": 1}) == [Output("z", 0, BOTTOM, None)]
    assert vals(m.step({"y": 2})) == {"z": BOTTOM}  # x + y had no value at tick 0
    assert vals(m.step({"x": 5})) == {"z": 3}
    assert [o.value for o in m.finish()] == [7]


# -- eval ordering ----------------------------------------------------------------------------


def test_eval_reads_streams_computed_before_it() -> None:
    m = mon("in s: Str\nin x: Int\naux a: Int\nout y: Int\ny = eval(s)\na = x * 2\n")
    assert vals(m.step({"s": "a + 1", "x": 3})) == {"y": 7}


def test_eval_cannot_read_itself_at_offset_zero() -> None:
    m = mon("in s: Str\nout y: Int\ny = eval(s)\n")
    with pytest.raises(EvalError, match=r"'y' is computed after 'y'.*y\[1\]"):
        m.step({"s": "y + 1"})
    assert vals(m.step({"s": "default(y[1], 0) + 1"})) == {"y": 1}
    assert vals(m.step({})) == {"y": 2}


def test_eval_of_an_unknown_stream() -> None:
    m = mon("in s: Str\nout y: Int\ny = eval(s)\n")
    with pytest.raises(EvalError, match="unknown stream 'nope'"):
        m.step({"s": "nope"})
    assert vals(m.step({})) == {"y": BOTTOM}  # the same bad text: no value
    assert vals(m.step({"s": "3"})) == {"y": 3}


# -- hot swap -----------------------------------------------------------------------------------


def test_swap_keeps_held_values_and_history() -> None:
    m = mon("in x: Int\nout y: Int\ny = x[1]\n")
    m.step({"x": 1})
    m.step({"x": 2})
    m2 = m.swap(load_spec("in x: Int\nout d: Int\nd = x[2] + x\n"))
    assert m2.tick == 2
    assert m2.step({}) == [Output("d", 2, 3, None)]  # x[2] = 1 (kept history), x held = 2


def test_swap_keeps_operator_state_of_unchanged_equations() -> None:
    src = "in x: Int\nin y: Bool\nout l: Int\nl = latch(x, y) + 1\nout w: Bool\nw = when(x)\n"
    m = mon(src)
    m.step({"x": 1})
    m.step({"y": True})
    m2 = m.swap(load_spec(src + "out extra: Int\nextra = 5\n"))
    assert vals(m2.step({"x": 7})) == {"l": 2, "w": True, "extra": 5}


def test_swap_to_a_bad_spec_leaves_the_runner_running() -> None:
    m = mon(SUM)
    m.step({"x": 1, "y": 1})
    bad = A.Spec(
        decls=(A.Decl("out", "z", A.TName("Int")),),
        equations=(A.Equation("z", A.Var("nope")),),
        order=("z",),
    )
    with pytest.raises(SpecError):
        m.swap(bad)
    assert vals(m.step({"x": 2})) == {"z": 3}


# -- real time ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("using", "expected"),
    [
        ("count", [1, 2, 2, 2, 1]),
        ("sum", [4, 6, 8, 6, 0]),
        ("avg", [4.0, 3.0, 4.0, 3.0, 0.0]),
        ("min", [4, 2, 2, 0, 0]),
        ("max", [4, 4, 6, 6, 0]),
    ],
)
def test_aggregate_over_a_time_window(using: str, expected: list[object]) -> None:
    m = mon(f"in x: Int\nin w: Int\nout a\na = x.aggregate(over: 2s, using: {using})\n")
    # the windows (t - 2s, t]: {4}, {4, 2}, {2, 6}, {6, 0}, {0} (at t=4 only w ticked)
    steps = [({"x": 4}, 0), ({"x": 2}, 1), ({"x": 6}, 2), ({"x": 0}, 3), ({"w": 0}, 4)]
    got = [vals(m.step(i, ts_ns=t * SEC))["a"] for i, t in steps]
    assert got == expected
    assert [type(v) for v in got] == [type(v) for v in expected]


def test_aggregate_empty_window() -> None:
    m = mon(
        "in x: Int\nin w: Int\nout a\nout c\na = x.aggregate(over: 1s, using: avg)\n"
        "c = x.aggregate(over: 1s, using: count)\n"
    )
    assert vals(m.step({"w": 1}, ts_ns=0)) == {"a": BOTTOM, "c": 0}
    m.step({"x": 3}, ts_ns=SEC)
    assert vals(m.step({"w": 1}, ts_ns=5 * SEC)) == {"a": BOTTOM, "c": 0}


def test_aggregate_window_is_bounded() -> None:
    m = mon(
        "in x: Int\nout c\nc = x.aggregate(over: 10s, using: count)\n",
        limits=Limits(window_samples=3),
    )
    for i in range(3):
        m.step({"x": i}, ts_ns=i)
    with pytest.raises(EvalError, match="more than 3 samples"):
        m.step({"x": 9}, ts_ns=4)


def test_aggregate_needs_timestamps() -> None:
    m = mon("in x: Int\nout c\nc = x.aggregate(over: 1s, using: count)\n")
    with pytest.raises(EvalError, match="needs tick timestamps"):
        m.step({"x": 1})


def test_timeout() -> None:
    m = mon("in mon: Int\nin ana: Int\nout late: Bool\nlate = timeout(ana, 2s)\n")
    seq = [
        ({"mon": 1}, 0, False),
        ({"mon": 1}, 2, False),
        ({"mon": 1}, 3, True),
        ({"ana": 1}, 4, False),
        ({"mon": 1}, 6, False),
        ({"mon": 1}, 7, True),
    ]
    for inputs, t, late in seq:
        assert vals(m.step(inputs, ts_ns=t * SEC)) == {"late": late}, t


def test_periodic_output_ticks_on_timer_ticks() -> None:
    m = mon("in x: Int\nout y: Int @ 1Hz\ny = x\n")
    assert m.next_due(0) == SEC
    assert vals(m.step({"x": 5}, ts_ns=SEC // 2)) == {"y": 5}
    assert m.step({}, ts_ns=SEC) == [Output("y", 1, 5, SEC)]  # due: the held value
    assert m.next_due(SEC) == 2 * SEC
    assert m.step({}, ts_ns=SEC + 10) == []  # not due yet
    assert m.step({}, ts_ns=3 * SEC + 1) == [Output("y", 3, 5, 3 * SEC + 1)]
    assert m.next_due(3 * SEC + 1) == 4 * SEC


def test_no_periodic_outputs_no_timer() -> None:
    assert mon(SUM).next_due(0) is None


# -- triggers and inspection ----------------------------------------------------------------------


def test_triggers_fire_while_their_condition_is_true() -> None:
    m = mon('in x: Int\nout y: Int\ny = x\ntrigger x > 3 "x too high" error\n')
    m.step({"x": 1}, ts_ns=10)
    assert m.fired == []
    m.step({"x": 5}, ts_ns=20)
    assert m.fired == [Fired("x too high", "error", 1, 20, 0)]
    m.step({}, ts_ns=30)  # held x is still 5
    assert m.fired == [Fired("x too high", "error", 2, 30, 0)]
    m.step({"x": 0})
    assert m.fired == []


def test_trigger_errors_name_the_trigger() -> None:
    m = mon('in x: Int\nout y: Int\ny = x\ntrigger 10 / x > 1 "big"\n')
    with pytest.raises(EvalError, match='trigger "big"'):
        m.step({"x": 0})


def test_nodes_are_inspectable() -> None:
    m = mon("in x: Int\nin y: Int\nout z: Bool\nz = x + y > 3\n")
    m.step({"x": 1, "y": 1})
    root = m.nodes["z"]
    assert isinstance(root.ast, A.Binary)
    assert root.ast.op == ">"
    assert root.value() is False
    plus = root.children[0]
    assert isinstance(plus.ast, A.Binary)
    assert plus.value() == 2
    assert [c.value() for c in plus.children] == [1, 1]
    assert m.value("z") is False
    assert m.held("x") == 1
