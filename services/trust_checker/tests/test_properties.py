"""Laws of the semantics, checked on random traces (hypothesis).

- A hot swap to the same spec is invisible: a trace split at any point and continued in
  ``m.swap(spec)`` gives exactly the outputs of the unsplit run.
- Sample and hold: ``z = x + y``, ``y = x[k]``, ``c = x`` and ``default(x[1], d)`` equal a
  direct Python computation over traces with random NoVal gaps.
"""

from __future__ import annotations

from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st
from trust_checker.engine import Output, SpecRunner
from trust_checker.lang import load_spec
from trust_checker.values import BOTTOM

SETTINGS = settings(max_examples=60, deadline=None)

STATEFUL = load_spec(
    """
in x: Int
in y: Int
in c: Bool
in s: Str
out sum: Int
out d: Int
out w: Bool
out l: Int
out u: Int
out i: Int
out n: Int
out f: Int
out e: Int
sum = x + y
d = default(x[2], -1) * y
w = when(y)
l = latch(x, c) + 1
u = update(x, y)
i = init(x, 0)
n = n[-1, 0] + 1
f = if c then x else y[1]
e = eval(s)
"""
)

ticks_st = st.lists(
    st.fixed_dictionaries(
        {},
        optional={
            "x": st.integers(-5, 5),
            "y": st.integers(-5, 5),
            "c": st.booleans(),
            "s": st.sampled_from(["x + 1", "x[1]", "y", "default(y[2], 0) * 2"]),
        },
    ),
    max_size=25,
)


def _run(m: SpecRunner, ticks: list[dict[str, Any]]) -> list[Output]:
    out: list[Output] = []
    for t in ticks:
        out += m.step(t)
    return out


@SETTINGS
@given(ticks=ticks_st, data=st.data())
def test_swap_to_the_same_spec_changes_nothing(ticks: list[dict[str, Any]], data: Any) -> None:
    k = data.draw(st.integers(0, len(ticks)), label="split")
    whole = SpecRunner(STATEFUL)
    expected = _run(whole, ticks) + whole.finish()
    first = SpecRunner(STATEFUL)
    got = _run(first, ticks[:k])
    second = first.swap(STATEFUL)
    got += _run(second, ticks[k:]) + second.finish()
    assert got == expected


gappy_ints = st.lists(st.one_of(st.none(), st.integers(-(2**40), 2**40)), max_size=30)


def _held(xs: list[int | None]) -> list[int | None]:
    out: list[int | None] = []
    last: int | None = None
    for v in xs:
        last = v if v is not None else last
        out.append(last)
    return out


@SETTINGS
@given(xs=gappy_ints, ys=gappy_ints)
def test_sum_holds_both_operands(xs: list[int | None], ys: list[int | None]) -> None:
    n = min(len(xs), len(ys))
    xs, ys = xs[:n], ys[:n]
    m = SpecRunner(load_spec("in x: Int\nin y: Int\nout z: Int\nz = x + y\n"))
    ticks = [
        {k: v for k, v in (("x", a), ("y", b)) if v is not None}
        for a, b in zip(xs, ys, strict=True)
    ]
    got = [(o.tick, o.value) for o in _run(m, ticks) + m.finish()]
    hx, hy = _held(xs), _held(ys)
    expected = [
        (t, a + b)
        for t, (a, b) in enumerate(zip(hx, hy, strict=True))
        if a is not None and b is not None
    ]
    assert got == expected


@SETTINGS
@given(xs=gappy_ints, k=st.integers(1, 3))
def test_offset_is_k_deferred_then_the_held_value(xs: list[int | None], k: int) -> None:
    m = SpecRunner(load_spec(f"in x: Int\nin w: Int\nout y: Int\ny = x[{k}]\n"))
    ticks = [{"x": v} if v is not None else {"w": 0} for v in xs]
    got = [(o.tick, o.value) for o in _run(m, ticks) + m.finish()]
    held = _held(xs)
    expected = []
    for t in range(len(xs) + k):
        past = held[t - k] if t - k >= 0 else None
        expected.append((t, BOTTOM if past is None else past))
    assert got == expected


@SETTINGS
@given(xs=gappy_ints, d=st.integers(-3, 3))
def test_d52_default_offset(xs: list[int | None], d: int) -> None:
    m = SpecRunner(load_spec(f"in x: Int\nin w: Int\nout y: Int\ny = x[-1, {d}]\n"))
    ticks = [{"x": v} if v is not None else {"w": 0} for v in xs]
    got = [o.value for o in _run(m, ticks) + m.finish()]
    held = [None, *_held(xs)]
    assert got == [d if v is None else v for v in held]


@SETTINGS
@given(xs=gappy_ints)
def test_bare_reference_ticks_only_with_its_stream(xs: list[int | None]) -> None:
    m = SpecRunner(load_spec("in x: Int\nin w: Int\nout c: Int\nc = x\n"))
    ticks = [{"x": v} if v is not None else {"w": 0} for v in xs]
    got = [(o.tick, o.value) for o in _run(m, ticks) + m.finish()]
    assert got == [(t, v) for t, v in enumerate(xs) if v is not None]
