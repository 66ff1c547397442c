"""The shipped MAPLE-K specs on hand-written trace files (tests/maplek_traces/), healthy
and faulty: each output is true on every tick of a healthy trace and false exactly on the
ticks a faulty trace's header names."""

from __future__ import annotations

from pathlib import Path

import pytest
from trust_checker.engine import SpecRunner
from trust_checker.lang import ast, load_spec
from trust_checker.lang.check import children
from trust_checker.specs import ANOMALY_DEADLINE_NS, MAPLEK_OUTPUTS, maplek_specs
from trust_checker.tracefile import read_trace

TRACES = Path(__file__).parent / "maplek_traces"


def verdicts(name: str, trace: str) -> list[object]:
    """The spec's one output at each tick of the trace file (``t_ms`` in a tick is its
    time, not an input; a tick with only ``t_ms`` is a timer tick)."""
    mon = SpecRunner(load_spec(maplek_specs()[name]))
    (out,) = mon.outputs
    ticks = read_trace((TRACES / trace).read_text(), trace)
    values: list[object] = []
    for i, tick in enumerate(ticks):
        inputs = dict(tick)
        t_ms = inputs.pop("t_ms", None)
        ts = None if t_ms is None else int(t_ms) * 1_000_000  # type: ignore[call-overload]
        outs = mon.step(inputs, ts)
        assert [o.stream for o in outs] == [out], f"tick {i}: {outs}"
        values.append(outs[0].value)
    assert mon.finish() == []
    return values


def false_at(values: list[object]) -> list[int]:
    assert all(type(v) is bool for v in values), values
    return [i for i, v in enumerate(values) if v is False]


CASES = [
    ("stage_order", [4, 9, 10]),
    ("no_overlap", [1, 2, 5, 6]),
    ("unread_overwrite", [2, 6]),
    ("execute_approved", [2, 3, 7]),
    ("anomaly_deadline", [3, 4, 9, 10, 11]),
]


@pytest.mark.parametrize(("name", "faulty_ticks"), CASES, ids=[c[0] for c in CASES])
def test_healthy_trace_stays_true(name: str, faulty_ticks: list[int]) -> None:
    values = verdicts(name, f"{name}_healthy.trace")
    assert len(values) > 10
    assert false_at(values) == []


@pytest.mark.parametrize(("name", "faulty_ticks"), CASES, ids=[c[0] for c in CASES])
def test_faulty_trace_is_caught_where_it_goes_wrong(name: str, faulty_ticks: list[int]) -> None:
    assert false_at(verdicts(name, f"{name}_faulty.trace")) == faulty_ticks


def test_the_library_is_five_specs_with_one_bool_output_each() -> None:
    specs = maplek_specs()
    assert set(specs) == set(MAPLEK_OUTPUTS)
    for name, text in specs.items():
        spec = load_spec(text)
        outs = [d for d in spec.decls if d.kind == "out"]
        assert [(d.name, d.type) for d in outs] == [(MAPLEK_OUTPUTS[name], ast.TName("Bool"))]
        assert text.startswith("//"), f"{name}: the spec opens with what it checks"


def _timeouts(e: ast.Expr) -> list[int]:
    found: list[int] = []
    if isinstance(e, ast.Call) and e.func == "timeout":
        lit = e.args[1]
        assert isinstance(lit, ast.Lit)
        assert type(lit.value) is int
        found.append(lit.value)
    for c in children(e):
        found += _timeouts(c)
    return found


def test_the_deadline_constant_matches_the_spec() -> None:
    spec = load_spec(maplek_specs()["anomaly_deadline"])
    limits = [ns for eq in spec.equations for ns in _timeouts(eq.expr)]
    assert limits == [ANOMALY_DEADLINE_NS]
    assert f"DEADLINE = {ANOMALY_DEADLINE_NS // 1_000_000}ms" in maplek_specs()["anomaly_deadline"]


def test_the_deadline_is_missed_without_any_input_only_by_timer_ticks() -> None:
    mon = SpecRunner(load_spec(maplek_specs()["anomaly_deadline"]))
    assert [o.value for o in mon.step({"ev_anomaly": "c1"}, 1_000)] == [True]
    due = mon.next_due(1_000)
    assert due == 1_000 + 100_000_000  # @ 10Hz
    seen: list[tuple[int | None, object]] = []
    while due is not None and due < 1_000 + 2 * ANOMALY_DEADLINE_NS:
        seen += [(o.ts_ns, o.value) for o in mon.step({}, due)]
        due = mon.next_due(due)
    first_false = next(ts for ts, v in seen if v is False)
    assert first_false is not None
    assert first_false - 1_000 == ANOMALY_DEADLINE_NS + 100_000_000  # the first tick past it


def test_memory_stays_bounded_over_many_cycles() -> None:
    """stage_order and execute_approved forget all but their last KEEP (256) cycles."""
    order = SpecRunner(load_spec(maplek_specs()["stage_order"]))
    approved = SpecRunner(load_spec(maplek_specs()["execute_approved"]))
    for i in range(600):
        c = f"c{i}"
        for stage in ("monitor", "analyse"):
            (o,) = order.step({"stage": stage, "phase": "start", "cycle": c})
            assert o.value is True
        approved.step({"ev_cycle": c, "verdict_approved": True})
        (o,) = approved.step({"execute_start": c, "acted": False})
        assert o.value is True
    reached = order.held("reached")
    assert isinstance(reached, dict)
    assert len(reached) == 256
    assert "c599" in reached
    assert "c0" not in reached
    seen = approved.held("verdicts")
    assert isinstance(seen, dict)
    assert len(seen) == 256
    # a forgotten cycle is a cycle never seen: its analyse is out of order
    (o,) = order.step({"stage": "analyse", "phase": "start", "cycle": "c0"})
    assert o.value is False
