"""Explanations: verdicts when a Bool output turns false, trigger firings, ``because``."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import msgspec
import pytest
from rap_schemas import TrustCause, TrustVerdict
from trust_checker.engine import SpecRunner
from trust_checker.errors import EvalError, InputError
from trust_checker.explain import Cause, ExplainedVerdict, Explainer, expr_text, to_message
from trust_checker.lang import load_spec, parse_expr
from trust_checker.values import BOTTOM

LATENCY = """\
in latency: Float
in approved: Bool
out ok: Bool
ok = latency < 2.0 && approved
"""


def explainer(spec: str, **kw: int) -> Explainer:
    return Explainer(SpecRunner(load_spec(spec)), **kw)


def run(
    spec: str | Explainer, ticks: Sequence[Mapping[str, object]], **kw: int
) -> list[ExplainedVerdict]:
    ex = explainer(spec, **kw) if isinstance(spec, str) else spec
    out: list[ExplainedVerdict] = []
    for i, t in enumerate(ticks):
        out += ex.step(t, 1_000 + i).verdicts
    return out


def because(v: ExplainedVerdict) -> list[tuple[object, ...]]:
    """Each cause as (depth, expr, value[, input, input_tick])."""
    return [
        (c.depth, c.expr, c.value)
        if c.input is None
        else (c.depth, c.expr, c.value, c.input, c.input_tick)
        for c in v.because
    ]


# -- output verdicts ------------------------------------------------------------------------


def test_a_false_and_names_the_false_operand_and_the_input_tick() -> None:
    ticks: list[dict[str, object]] = [{"latency": 1.0}, {"approved": True}]
    ticks += [{"approved": True}] * 39  # ticks 2..40: still fine
    ticks.append({"latency": 2.7})  # tick 41
    (v,) = run(LATENCY, ticks)
    assert (v.stream, v.tick, v.ts_ns, v.value, v.kind) == ("ok", 41, 1_041, False, "output")
    assert v.expr == "latency < 2.0 && approved"
    assert because(v) == [
        (0, "latency < 2.0", False),
        (1, "latency", 2.7, "latency", 41),
    ]
    assert not v.truncated
    assert v.describe() == (
        "ok[41] = Bool(false): latency < 2.0 && approved\n"
        "  because latency < 2.0 = Bool(false)\n"
        "    because latency = Float(2.7) (input latency, tick 41)"
    )


def test_no_verdict_while_true_and_one_only_on_each_turn_to_false() -> None:
    ex = explainer(LATENCY)
    seen: list[tuple[int, list[str]]] = []
    ticks: list[dict[str, object]] = [
        {"latency": 1.0, "approved": True},  # 0 true
        {"latency": 1.5},  # 1 true
        {"approved": False},  # 2 false: a verdict
        {"latency": 3.0},  # 3 still false: none
        {"approved": True},  # 4 still false (latency): none
        {"latency": 1.0},  # 5 true
        {"latency": 9.0},  # 6 false again: a verdict
    ]
    for t in ticks:
        outs, verdicts = ex.step(t)
        assert len(outs) == 1
        seen += [(v.tick, [c.expr for c in v.because]) for v in verdicts]
    assert seen == [(2, ["approved"]), (6, ["latency < 2.0", "latency"])]


def test_false_as_first_value_and_after_bottom_are_turns() -> None:
    spec = "in x: Int\nout first: Bool\nfirst = x > 0\nout late: Bool\nlate = x[1] > 0\n"
    verdicts = run(spec, [{"x": 0}, {"x": 5}, {"x": 0}, {"x": 7}])
    # first: false at 0 (no value before), true at 1, false at 2;
    # late: ⊥ at 0, false at 1 (x[1] = 0), true at 2, false at 3 (x[1] = 0 from tick 2)
    assert [(v.stream, v.tick) for v in verdicts] == [
        ("first", 0),
        ("late", 1),
        ("first", 2),
        ("late", 3),
    ]
    assert because(verdicts[1]) == [(0, "x[1]", 0, "x", 0)]
    assert because(verdicts[3]) == [(0, "x[1]", 0, "x", 2)]


def test_outputs_that_are_not_bool_and_aux_streams_give_no_verdict() -> None:
    spec = 'in x: Int\nout n: Int\nn = x - 1\naux low: Bool\nlow = x > 5\nout s: Str\ns = "a"\n'
    assert run(spec, [{"x": 1}, {"x": 0}]) == []


def test_or_lists_every_operand_and_both_false_operands_of_and() -> None:
    spec = """\
in a: Int
in b: Int
out either: Bool
either = a > 0 || b > 0
out both: Bool
both = a > 0 && b > 0
"""
    verdicts = run(spec, [{"a": 0}, {"b": -1}])
    assert [(v.stream, v.tick) for v in verdicts] == [("either", 1), ("both", 1)]
    expected = [(0, "a > 0", False), (1, "a", 0, "a", 0), (0, "b > 0", False), (1, "b", -1, "b", 1)]
    assert because(verdicts[0]) == expected
    assert because(verdicts[1]) == expected


def test_if_gives_the_condition_and_the_branch_taken_only() -> None:
    spec = """\
in mode: Str
in speed: Float
in limit: Float
out safe: Bool
safe = if mode == "fast" then speed < limit * 2.0 else speed < limit
"""
    ticks: list[dict[str, object]] = [
        {"mode": "slow", "speed": 1.0, "limit": 2.0},
        {"speed": 3.0},  # tick 1: slow branch false
    ]
    (v,) = run(spec, ticks)
    assert because(v) == [
        (0, 'mode == "fast"', False),
        (1, "mode", "slow", "mode", 0),
        (0, "speed < limit", False),
        (1, "speed", 3.0, "speed", 1),
        (1, "limit", 2.0, "limit", 0),
    ]


def test_a_computed_stream_is_followed_into_its_equation() -> None:
    spec = """\
in latency: Float
in approved: Bool
aux fast: Bool
fast = (latency + 0.5) * 2.0 < 5.0   // a comment
out ok: Bool
ok = fast || approved
"""
    (v,) = run(spec, [{"latency": 1.0, "approved": False}, {"latency": 2.5}])
    assert v.tick == 1
    assert because(v) == [
        (0, "fast", False),
        (1, "(latency + 0.5) * 2.0 < 5.0", False),
        (2, "(latency + 0.5) * 2.0", 6.0),
        (3, "latency + 0.5", 3.0),
        (4, "latency", 2.5, "latency", 1),
        (0, "approved", False, "approved", 0),
    ]


def test_d52_defaults_and_past_values_name_the_tick_the_value_arrived() -> None:
    spec = """\
in x: Int
out rising: Bool
rising = x > x[-2, 0]
"""
    ticks: list[dict[str, object]] = [{"x": 3}, {"x": 5}, {}, {"x": 4}, {}, {"x": 9}, {}, {"x": 1}]
    verdicts = run(spec, ticks)
    # x[-2, 0] is x two ticks back: at tick 3 that is 5 (arrived at tick 1), at tick 7 it
    # is 9 (arrived at tick 5); at tick 4 it is 5 again: still false, no verdict
    assert [v.tick for v in verdicts] == [3, 7]
    assert because(verdicts[0]) == [(0, "x", 4, "x", 3), (0, "x[-2, 0]", 5, "x", 1)]
    assert because(verdicts[1]) == [(0, "x", 1, "x", 7), (0, "x[-2, 0]", 9, "x", 5)]
    ex = explainer(spec)
    (v,) = run(ex, [{"x": -1}])  # tick 0: no past value, the default decides
    assert because(v) == [(0, "x", -1, "x", 0), (0, "x[-2, 0]", 0, "x", None)]


def test_an_input_output_and_a_negation_are_their_own_reason() -> None:
    spec = "in ok: Bool\nout same: Bool\nsame = ok\nout failed: Bool\nfailed = !ok\n"
    verdicts = run(spec, [{"ok": True}, {"ok": False}])
    assert [(v.stream, v.tick, because(v)) for v in verdicts] == [
        ("failed", 0, [(0, "ok", True, "ok", 0)]),
        ("same", 1, [(0, "ok", False, "ok", 1)]),
    ]


def test_source_text_of_not_equal_negative_literals_calls_and_lists() -> None:
    spec = """\
in x: Int
in s: Str
in l: List<Int>
out ok: Bool
ok = (s != "bad") && abs(x) < -(-3) && List.len(l) >= 2 && default(x[2], -1) != -1
"""
    (v,) = run(spec, [{"x": 1, "s": "bad", "l": (1,)}])
    assert [(c.depth, c.expr) for c in v.because] == [
        (0, 's != "bad"'),
        (1, "s"),
        (0, "List.len(l) >= 2"),
        (1, "List.len(l)"),
        (2, "l"),
        (0, "default(x[2], -1) != -1"),
        (1, "default(x[2], -1)"),
        (2, "x[2]"),
    ]
    assert v.because[-1].value is BOTTOM  # x two ticks back: none
    assert v.because[-1].input == "x"
    assert v.because[-1].input_tick is None


def test_bottom_is_explained_by_the_bottom_operand() -> None:
    spec = "in x: Int\nin y: Int\nout ok: Bool\nok = default(x[1] > 0 && y > 0, false)\n"
    (v,) = run(spec, [{"x": 1, "y": 0}])
    assert because(v) == [
        (0, "x[1] > 0 && y > 0", BOTTOM),
        (1, "x[1] > 0", BOTTOM),
        (2, "x[1]", BOTTOM, "x", None),
    ]
    wire = to_message(v).because
    assert wire[0] == TrustCause(expr="x[1] > 0 && y > 0", value=None, deferred=True)


def test_because_is_bounded() -> None:
    terms = " && ".join(f"x{i} > 0" for i in range(10))
    spec = "".join(f"in x{i}: Int\n" for i in range(10)) + f"out all: Bool\nall = {terms}\n"
    (v,) = run(spec, [{f"x{i}": 0 for i in range(10)}], max_causes=5)
    assert len(v.because) == 5
    assert v.truncated
    assert [c.expr for c in v.because] == ["x0 > 0", "x0", "x1 > 0", "x1", "x2 > 0"]
    (deep,) = run(spec.replace("x0 > 0", "-(-(-x0)) > 0"), [{f"x{i}": 0 for i in range(10)}])
    assert deep.because[0].expr == "-(-(-x0)) > 0"
    (shallow,) = run(
        spec.replace("x0 > 0", "-(-(-x0)) > 0"), [{f"x{i}": 0 for i in range(10)}], max_depth=2
    )
    assert [(c.depth, c.expr) for c in shallow.because][:2] == [
        (0, "-(-(-x0)) > 0"),
        (1, "-(-(-x0))"),
    ]
    assert shallow.truncated


def test_a_spec_without_source_text_is_written_out_from_the_tree() -> None:
    spec = dataclasses.replace(load_spec(LATENCY), source="")
    ex = Explainer(SpecRunner(spec))
    (v,) = run(ex, [{"latency": 3.0, "approved": True}])
    assert v.expr == "latency < 2.0 && approved"
    assert [c.expr for c in v.because] == ["latency < 2.0", "latency"]


@pytest.mark.parametrize(
    "text",
    [
        "a + b * c",
        "(a + b) * c",
        "a - (b - c)",
        "!(a && b) || c",
        "a != b",
        "if a then b else c",
        "(if a then b else c) + 1",
        "x[2]",
        "default(x[1], -1.5)",
        'Map("k": 1)',
        "{a: 1, b: [1, 2]}",
        "(1, true).0",
        "a => b => c",
        "(a => b) => c",
        '"q\\"uote" ++ s',
        "timeout(x, 2000000000ns)",
    ],
)
def test_expr_text_round_trips(text: str) -> None:
    tree = parse_expr(text)
    again = expr_text(tree)
    assert parse_expr(again) == tree, again


# -- triggers ---------------------------------------------------------------------------------


def test_triggers_give_verdicts_with_message_and_severity_on_every_firing() -> None:
    spec = """\
in latency: Float
in approved: Bool
trigger latency > 2.5 && approved "too slow" critical
trigger !approved "not approved"
trigger !approved "not approved" info
"""
    ticks: list[dict[str, object]] = [
        {"latency": 1.0, "approved": True},  # 0: nothing
        {"latency": 3.0},  # 1: too slow
        {"latency": 3.5},  # 2: too slow again (a trigger fires on every tick)
        {"approved": False},  # 3: not approved, twice (two triggers)
    ]
    verdicts = run(spec, ticks)
    assert [(v.stream, v.tick, v.kind, v.message, v.severity) for v in verdicts] == [
        ("trigger.0", 1, "trigger", "too slow", "critical"),
        ("trigger.0", 2, "trigger", "too slow", "critical"),
        ("trigger.1", 3, "trigger", "not approved", "warning"),
        ("trigger.2", 3, "trigger", "not approved", "info"),
    ]
    assert all(v.value is True for v in verdicts)
    assert verdicts[0].expr == "latency > 2.5 && approved"
    assert because(verdicts[0]) == [
        (0, "latency > 2.5", True),
        (1, "latency", 3.0, "latency", 1),
        (0, "approved", True, "approved", 0),
    ]
    assert because(verdicts[2]) == [(0, "approved", False, "approved", 3)]
    msg = to_message(verdicts[0])
    assert (msg.kind, msg.message, msg.severity, msg.value) == (
        "trigger",
        "too slow",
        "critical",
        True,
    )


def test_triggers_with_the_same_message_are_told_apart_by_their_condition() -> None:
    spec = 'in x: Int\ntrigger x > 10 "odd value"\ntrigger x < 0 "odd value"\n'
    verdicts = run(spec, [{"x": 5}, {"x": -1}, {"x": 11}])
    assert [(v.stream, v.tick, v.expr) for v in verdicts] == [
        ("trigger.1", 1, "x < 0"),
        ("trigger.0", 2, "x > 10"),
    ]


def test_an_or_that_is_true_lists_only_the_true_operands() -> None:
    spec = 'in a: Int\nin b: Int\ntrigger a > 0 || b > 0 "some positive"\n'
    (v,) = run(spec, [{"a": 0, "b": 4}])
    assert because(v) == [(0, "b > 0", True), (1, "b", 4, "b", 0)]


def test_an_implication_that_is_false_names_both_sides() -> None:
    spec = "in a: Bool\nin b: Bool\nout rule: Bool\nrule = a => b\n"
    (v,) = run(spec, [{"a": True, "b": False}])
    assert because(v) == [(0, "a", True, "a", 0), (0, "b", False, "b", 0)]


# -- the wrapper ------------------------------------------------------------------------------


def test_the_wire_form_round_trips_as_json() -> None:
    (v,) = run(LATENCY, [{"latency": 2.7, "approved": True}])
    msg = to_message(v)
    assert msg == TrustVerdict(
        stream="ok",
        tick=0,
        ts=1_000,
        value=False,
        expr="latency < 2.0 && approved",
        because=[
            TrustCause(expr="latency < 2.0", value=False),
            TrustCause(expr="latency", value=2.7, depth=1, input="latency", input_tick=0),
        ],
    )
    wire = msgspec.json.encode(msg)
    assert msgspec.json.decode(wire, type=TrustVerdict) == msg
    assert msgspec.json.decode(wire)["because"][1] == {
        "expr": "latency",
        "value": 2.7,
        "depth": 1,
        "input": "latency",
        "input_tick": 0,
    }


def test_refused_inputs_are_not_arrivals_and_failed_ticks_are() -> None:
    spec = "in x: Int\nin y: Int\nout ok: Bool\nok = 10 / y > x\n"
    ex = explainer(spec)
    with pytest.raises(InputError):
        ex.step({"x": "text"})
    with pytest.raises(EvalError):
        ex.step({"x": 1, "y": 0})  # tick 0: division by zero
    outs, verdicts = ex.step({"y": 5})  # tick 1: 10 / 5 > 1 is true
    assert [o.value for o in outs] == [True]
    outs, verdicts = ex.step({"y": 20})  # tick 2: 0 > 1 is false
    (v,) = verdicts
    assert because(v) == [
        (0, "10 / y", 0),
        (1, "y", 20, "y", 2),
        (0, "x", 1, "x", 0),  # x arrived with the tick that failed
    ]


def test_swap_carries_arrival_ticks_and_last_values_over() -> None:
    ex = explainer(LATENCY)
    run(ex, [{"latency": 1.0, "approved": True}, {"latency": 1.2}])
    new = ex.swap(load_spec(LATENCY.replace("2.0", "1.1")))
    assert new.runner.tick == 2
    (v,) = new.step({"approved": True}).verdicts  # 1.2 < 1.1 is false: a turn
    assert because(v) == [(0, "latency < 1.1", False), (1, "latency", 1.2, "latency", 1)]
    assert new.step({"approved": True}).verdicts == []  # still false: no new verdict


def test_each_drain_tick_is_explained_at_its_own_tick() -> None:
    spec = "in x: Bool\nout y: Bool\ny = x[2]\n"
    ex = explainer(spec)
    for t in ({"x": True}, {"x": False}, {"x": False}):
        assert ex.step(t).verdicts == []
    outs, verdicts = ex.finish()
    assert [(o.tick, o.value) for o in outs] == [(3, False), (4, False)]
    (v,) = verdicts  # y turned false at tick 3, the first of two drain ticks
    assert v.tick == 3
    assert not v.truncated
    assert because(v) == [(0, "x[2]", False, "x", 1)]
    assert ex.finish() == ([], [])  # idempotent
    spec2 = "in x: Bool\nout y: Bool\ny = x[1]\n"
    ex = explainer(spec2)
    ex.step({"x": True})
    ex.step({"x": False})
    (v,) = ex.finish().verdicts  # y = false at tick 2, the last drain tick
    assert because(v) == [(0, "x[1]", False, "x", 1)]


def test_a_trigger_firing_at_an_earlier_drain_tick_is_kept_and_explained() -> None:
    spec = 'in x: Int\ntrigger x[2] > 5 "late"\ntrigger x[1] > 5 "late"\n'
    ex = explainer(spec)
    ex.step({"x": 9})
    ex.step({"x": 1})
    _, verdicts = ex.finish()  # drain tick 2: x[2] = 9; tick 3: x[2] = 1, x[1] = ⊥
    assert [(v.stream, v.tick, v.message) for v in verdicts] == [("trigger.0", 2, "late")]
    assert because(verdicts[0]) == [(0, "x[2]", 9, "x", 0)]
    mon = SpecRunner(load_spec(spec))
    mon.step({"x": 9})
    mon.step({"x": 1})
    mon.finish()  # SpecRunner.fired: every drain tick's firings, not only the last one's
    assert [(f.tick, f.trigger, f.message) for f in mon.fired] == [(2, 0, "late")]


def test_cause_describe_names_missing_input_values() -> None:
    c = Cause("x[1]", BOTTOM, 0, "x", None)
    assert c.describe() == "x[1] = Deferred (input x, no value yet)"


def test_finish_without_drain_ticks_repeats_no_trigger() -> None:
    ex = explainer('in x: Int\ntrigger x > 1 "big"\n')
    assert [v.tick for v in ex.step({"x": 5}).verdicts] == [0]
    assert ex.finish() == ([], [])


def test_subexpressions_that_read_no_stream_are_not_reasons() -> None:
    spec = "in x: Float\nout ok: Bool\nok = x * (1.0 + 1.0) < 2.0 * 3.0\n"
    (v,) = run(spec, [{"x": 4.0}])
    assert because(v) == [(0, "x * (1.0 + 1.0)", 8.0), (1, "x", 4.0, "x", 0)]
